"""Contrast-driven level of detail: spend work only where a viewer could see it (docs/lod.md)."""
