"""The displays this machine has attached, as SDL (through pygame-ce, the window sink's library)
sees them: index (what `sink.display` takes), name, desktop size, and the refresh rates it offers.

    found = attached_displays()
    found.problem   # why there are none ("" when there are)
    found.displays  # [Display(index=0, name="DELL U2720Q", size=(3840, 2160), refresh_hz=(60,)), ...]

Without a display server SDL falls back to its "offscreen" or "dummy" video driver, which invents a
1024×768 screen: that is reported as no display, never as a display. Names and per-mode refresh
rates come from the SDL library pygame-ce loaded (`SDL_GetDisplayName`, `SDL_GetDisplayMode`);
where that library cannot be reached, the name is empty and the refresh is the desktop's alone.
"""

from __future__ import annotations

import ctypes
import os
from dataclasses import dataclass

__all__ = ["Display", "DisplayList", "attached_displays"]

NO_DISPLAY_DRIVERS = ("offscreen", "dummy")


@dataclass(frozen=True)
class Display:
    index: int
    name: str
    size: tuple[int, int]  # the desktop's (current) mode
    refresh_hz: tuple[int, ...]  # at the desktop size, the current first; () when SDL does not say


@dataclass(frozen=True)
class DisplayList:
    driver: str
    displays: tuple[Display, ...]
    problem: str = ""  # why there are no displays


class _Mode(ctypes.Structure):
    _fields_ = [("format", ctypes.c_uint32), ("w", ctypes.c_int), ("h", ctypes.c_int),
                ("refresh_rate", ctypes.c_int), ("driverdata", ctypes.c_void_p)]


def _loaded_sdl():
    """The SDL2 library this process has loaded (pygame-ce's own copy), or None."""
    try:
        with open("/proc/self/maps") as f:
            paths = {line.split()[-1] for line in f if "libSDL2-2" in line or "libSDL2.so" in line}
    except OSError:
        return None
    for path in sorted(paths):
        try:
            sdl = ctypes.CDLL(path)
            sdl.SDL_GetDisplayName.restype = ctypes.c_char_p
            sdl.SDL_GetDisplayName.argtypes = [ctypes.c_int]
            sdl.SDL_GetNumDisplayModes.argtypes = [ctypes.c_int]
            sdl.SDL_GetDisplayMode.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.POINTER(_Mode)]
            return sdl
        except (OSError, AttributeError):
            continue
    return None


def _refresh_rates(sdl, index: int, size: tuple[int, int], current: int) -> tuple[int, ...]:
    rates = [current] if current > 0 else []
    if sdl is not None:
        mode = _Mode()
        for m in range(max(0, sdl.SDL_GetNumDisplayModes(index))):
            if sdl.SDL_GetDisplayMode(index, m, ctypes.byref(mode)) == 0 and (mode.w, mode.h) == size \
                    and mode.refresh_rate > 0:
                rates.append(mode.refresh_rate)
    return tuple(dict.fromkeys(rates))


def attached_displays() -> DisplayList:
    """Every display SDL reports, or none with the reason (no pygame-ce, no display server)."""
    os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
    try:
        import pygame
    except ImportError:
        return DisplayList("", (), "pygame-ce is not installed: pip install 'dpmhw[display]'")
    try:
        pygame.display.init()
    except pygame.error as exc:
        return DisplayList("", (), f"no display: SDL cannot start a video driver ({exc})")
    try:
        driver = pygame.display.get_driver()
        if driver in NO_DISPLAY_DRIVERS:
            where = os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
            return DisplayList(driver, (), f"no display: SDL found no display server (DISPLAY/WAYLAND_DISPLAY "
                                           f"{'= ' + where if where else 'unset'}; video driver {driver!r})")
        sdl = _loaded_sdl()
        sizes = pygame.display.get_desktop_sizes()
        rates = pygame.display.get_desktop_refresh_rates()
        out = []
        for i, size in enumerate(sizes):
            name = sdl.SDL_GetDisplayName(i) if sdl is not None else None
            out.append(Display(i, (name or b"").decode("utf-8", "replace"), tuple(size),
                               _refresh_rates(sdl, i, tuple(size), int(rates[i]) if i < len(rates) else 0)))
        return DisplayList(driver, tuple(out), "" if out else f"no display: the {driver} video driver lists none")
    finally:
        pygame.display.quit()
