"""Benchmarks behind `dpmhw bench …`: each returns a result dict and prints a table."""
