"""Embree 4's C API, called from inside the numba kernels (no Python between ray queries).

The `embreex` wheel ships Embree 4 as `site-packages/embreex.libs/libembree4-<hash>.so.4`. This
module loads that library into the process with llvmlite (before any kernel is compiled or loaded
from the cache), so the kernels can call `rtcIntersect1/16` and `rtcOccluded1/16` by symbol name:
they are declared as numba ExternalFunctions with pointers passed as int64, which keeps
`cache=True` working (no ctypes address is baked into the compiled code). Scenes are built
through ctypes with shared vertex (16-byte stride) and index buffers that this module keeps
alive as long as the scene.

Layouts of this build (instance arrays compiled in): RTCRayHit is 96 bytes, RTCRay 48,
RTCRayHit16 1344, RTCRay16 768. Masks are compiled in (mask must be all ones), geomID/instID
must be RTC_INVALID_GEOMETRY_ID before each call, an occluded ray returns tfar = −inf, and
packets and their valid arrays need 64-byte alignment (numba's np.empty does not give it).
"""

from __future__ import annotations

import ctypes
import glob
import os
import warnings

import numba as nb
import numpy as np
from numba import types

# RTCRayHit / RTCRay word offsets (4-byte words): org 0-2, tnear 3, dir 4-6, time 7, tfar 8,
# mask 9, id 10, flags 11, then the hit: Ng 12-14, u 15, v 16, primID 17, geomID 18, instID 19
R_TNEAR, R_TIME, R_TFAR, R_MASK, R_ID, R_FLAGS = 3, 7, 8, 9, 10, 11
H_U, H_V, H_PRIM, H_GEOM, H_INST = 15, 16, 17, 18, 19
# A W-wide packet (RTCRayHit16: W = 16) has field k of lane j at word W * k + j: the RTCRayHit
# above is the 1-wide case (its 20 words padded to 24).
P16_RAYHIT_WORDS = 336
INVALID = -1  # RTC_INVALID_GEOMETRY_ID (0xFFFFFFFF) as int32; also "all mask bits"

RTC_GEOMETRY_TYPE_TRIANGLE = 0
RTC_BUFFER_TYPE_INDEX, RTC_BUFFER_TYPE_VERTEX = 0, 1
RTC_FORMAT_UINT3, RTC_FORMAT_FLOAT3 = 0x5003, 0x9003
RTC_SCENE_FLAG_ROBUST = 1 << 2
# The robust flag (watertight traversal and Pluecker intersection) is off, by measurement
# (paper-static, 2 threads, alternated): it cost 21 CPU-ms of a 232 CPU-ms fixed
# frame and 31 of 285 with the camera moving (9-11 %). On 3.0M continuation and 4.0M shadow rays
# of four real frames, dropping it changed the primitive of 7 hits (neighbouring triangles across
# an edge), let none escape and unblocked no shadow ray; the furnace, closed-box and grazing tests
# hold. Rays aimed exactly at a closed box's edges from inside still escape without it (832 of
# 60,000: tests/render/test_embree.py::test_no_leak_out_of_a_closed_box); paths never aim that
# exactly, and random bounces do not leak (same test). No accel of this build is both
# watertight and faster: "tri_accel=bvh8.triangle4v" (and every robust variant) is the Pluecker
# test with robust traversal, as slow as the flag; the speed-up is the Moeller test's.
ROBUST = False

_lib: ctypes.CDLL | None = None
_device = None
_missing_reason: str | None = None


def library_path() -> str | None:
    """Path of the libembree4 that the embreex wheel ships (the hash in its name changes)."""
    try:
        import embreex
    except ImportError:
        return None
    site = os.path.dirname(os.path.dirname(os.path.abspath(embreex.__file__)))
    found = sorted(glob.glob(os.path.join(site, "embreex.libs", "libembree4*.so*")))
    return found[0] if found else None


def load() -> bool:
    """Load libembree4 into the process (idempotent). False, with one warning, if it is missing:
    the renderer then falls back to embreex's one-ray-per-call path."""
    global _lib, _device, _missing_reason
    if _lib is not None:
        return True
    if _missing_reason is not None:
        return False
    path = os.environ.get("DPMHW_EMBREE_LIB") or library_path()
    if os.environ.get("DPMHW_EMBREE_LIB") == "none":
        path = None
    if path is None or not os.path.exists(path):
        _missing_reason = "libembree4 not found in site-packages/embreex.libs"
    else:
        try:
            import llvmlite.binding as llvm

            llvm.load_library_permanently(path)
            lib = ctypes.CDLL(path)
            _declare(lib)
            isa = os.environ.get("DPMHW_EMBREE_ISA")  # e.g. avx2: what an AVX2 machine runs (dpmhw.machine)
            device = lib.rtcNewDevice(f"isa={isa}".encode() if isa else None)
            if not device:
                raise OSError(f"rtcNewDevice failed (error {lib.rtcGetDeviceError(None)})")
            _lib, _device = lib, device
            return True
        except (OSError, AttributeError) as exc:
            _missing_reason = f"could not load {path}: {exc}"
    warnings.warn(f"Embree C API unavailable ({_missing_reason}); using embreex's one-ray path (slower)", RuntimeWarning, stacklevel=2)
    return False


def _declare(lib: ctypes.CDLL) -> None:
    p, u32, sz = ctypes.c_void_p, ctypes.c_uint, ctypes.c_size_t
    for name, res, args in (
        ("rtcNewDevice", p, [ctypes.c_char_p]),
        ("rtcGetDeviceError", ctypes.c_int, [p]),
        ("rtcNewScene", p, [p]),
        ("rtcSetSceneFlags", None, [p, ctypes.c_int]),
        ("rtcSetSceneBuildQuality", None, [p, ctypes.c_int]),
        ("rtcNewGeometry", p, [p, ctypes.c_int]),
        ("rtcSetSharedGeometryBuffer", None, [p, ctypes.c_int, u32, ctypes.c_int, p, sz, sz, sz]),
        ("rtcCommitGeometry", None, [p]),
        ("rtcAttachGeometry", u32, [p, p]),
        ("rtcReleaseGeometry", None, [p]),
        ("rtcCommitScene", None, [p]),
        ("rtcReleaseScene", None, [p]),
    ):
        fn = getattr(lib, name)
        fn.restype, fn.argtypes = res, args


class RtcScene:
    """One Embree scene of triangle meshes (one geometry per mesh, geomID = list position),
    built through ctypes. `handle` is the RTCScene pointer for the kernels (0 once closed)."""

    def __init__(self, vertices_list, faces_list, robust: bool | None = None):
        if not load():
            raise RuntimeError(f"Embree C API unavailable: {_missing_reason}")
        lib = _lib
        self._buffers = []  # shared with Embree: must outlive the scene
        scene = lib.rtcNewScene(_device)
        if ROBUST if robust is None else robust:
            lib.rtcSetSceneFlags(scene, RTC_SCENE_FLAG_ROBUST)
        for vertices, faces in zip(vertices_list, faces_list):
            v = np.zeros((len(vertices), 4), np.float32)  # 16-byte stride (Embree reads 16 bytes per vertex)
            v[:, :3] = vertices
            f = np.ascontiguousarray(faces, np.uint32)
            geom = lib.rtcNewGeometry(_device, RTC_GEOMETRY_TYPE_TRIANGLE)
            lib.rtcSetSharedGeometryBuffer(geom, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3, v.ctypes.data, 0, 16, len(v))
            lib.rtcSetSharedGeometryBuffer(geom, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3, f.ctypes.data, 0, 12, len(f))
            lib.rtcCommitGeometry(geom)
            lib.rtcAttachGeometry(scene, geom)
            lib.rtcReleaseGeometry(geom)  # the scene holds its own reference
            self._buffers += [v, f]
        lib.rtcCommitScene(scene)
        error = lib.rtcGetDeviceError(_device)
        if error:
            lib.rtcReleaseScene(scene)
            raise RuntimeError(f"Embree scene build failed (RTCError {error})")
        self.handle = int(scene)

    def close(self) -> None:
        if self.handle:
            _lib.rtcReleaseScene(ctypes.c_void_p(self.handle))
            self.handle = 0
            self._buffers = []

    def __del__(self):
        try:
            self.close()
        except Exception:  # interpreter shutdown
            pass


# ---- the C functions, callable from nopython code (pointers as int64) -------------------------
_i64 = types.int64
rtcIntersect1 = types.ExternalFunction("rtcIntersect1", types.void(_i64, _i64, _i64))
rtcOccluded1 = types.ExternalFunction("rtcOccluded1", types.void(_i64, _i64, _i64))
rtcIntersect16 = types.ExternalFunction("rtcIntersect16", types.void(_i64, _i64, _i64, _i64))
rtcOccluded16 = types.ExternalFunction("rtcOccluded16", types.void(_i64, _i64, _i64, _i64))


@nb.njit(nogil=True, cache=True)
def aligned_words(nwords, align=64):
    """A float32 scratch array of `nwords` starting on an `align`-byte boundary (over-allocate and
    offset; the view keeps its parent alive, and numba frees both with it)."""
    buf = np.empty(nwords + align // 4, np.float32)
    addr = buf.ctypes.data
    off = ((align - addr % align) % align) // 4
    return buf[off : off + nwords]
