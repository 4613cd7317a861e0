"""Pattern images for the DLPC900's pattern-on-the-fly mode: bit-plane packing, enhanced RLE, header.

The controller stores patterns as 24-bit images; each pixel is a 24-bit value sent as three
bytes, most significant byte first (the third byte holds bit positions 0-7, as in the header's
"BB GG RR" background and in hardware-proven hosts; docs/projector.md), and pattern k of
an image occupies bit position k (for 1-bit patterns) or bits [p, p + depth) for deeper ones
(DLPU018 "pattern number mapping").

Enhanced RLE (DLPU018 §2.4.4, "Enhanced Run-Length Encoding"), the only compression worth
sending over a 64-byte-report USB 1.1 link:

    n (n >= 1), pixel          repeat the pixel n times
    00 00                      end of line
    00 01 n                    copy n pixels from the line above (n >= 1)
    00 01 00                   end of image
    00 n (n >= 2), n pixels    n pixels sent uncompressed

A count below 128 takes one byte; from 128 on it takes two: (n & 0x7F) | 0x80, then n >> 7.
(The guide's worked example prints "82 01" as 513 repetitions, which contradicts its own rule;
the rule, which public host code also follows, gives 130.)

Everything here is vectorised: no Python loop runs per pixel or per run.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

SIGNATURE = b"Spld"
HEADER_SIZE = 48
COMPRESSION_NONE = 0
COMPRESSION_RLE = 1
COMPRESSION_ERLE = 2
MAX_COUNT = 0x7FFF  # largest count the two-byte form can carry


@dataclass(frozen=True)
class EncodedImage:
    """One pattern image as it goes over the wire: 48-byte header + pixel data."""

    width: int
    height: int
    compression: int
    data: bytes  # header + payload

    @property
    def payload_size(self) -> int:
        return len(self.data) - HEADER_SIZE


def image_header(width: int, height: int, payload_size: int, compression: int = COMPRESSION_ERLE,
                 background_bgr: tuple[int, int, int] = (0, 0, 0)) -> bytes:
    """The 48-byte header that precedes every pattern image (DLPU018 "image header")."""
    if not (0 < width <= 0xFFFF and 0 < height <= 0xFFFF):
        raise ValueError(f"image size: expected 1..65535 per side, got {width}x{height}")
    if compression not in (COMPRESSION_NONE, COMPRESSION_RLE, COMPRESSION_ERLE):
        raise ValueError(f"compression: expected 0, 1 or 2, got {compression}")
    b, g, r = background_bgr
    header = (SIGNATURE + struct.pack("<HHI", width, height, payload_size) + b"\xff" * 8
              + bytes((b, g, r, 0)) + bytes((0, compression, 1)) + bytes(21))
    assert len(header) == HEADER_SIZE
    return header


def pack_patterns(patterns: np.ndarray, bit_depth: int = 1) -> np.ndarray:
    """Pack up to 24 // bit_depth patterns into the bit planes of one 24-bit image.

    Parameters
    ----------
    patterns : (n, H, W) bool or uint8; values below 2**bit_depth. Pattern k lands on bits
        [k * bit_depth, (k + 1) * bit_depth).

    Returns
    -------
    image : (H, W) uint32, values below 2**24
    """
    patterns = np.asarray(patterns)
    if patterns.ndim != 3:
        raise ValueError(f"patterns: expected shape (n, H, W), got {patterns.shape}")
    if bit_depth not in range(1, 9):
        raise ValueError(f"bit_depth: expected 1..8, got {bit_depth}")
    n = patterns.shape[0]
    per_image = 24 // bit_depth
    if not 1 <= n <= per_image:
        raise ValueError(f"patterns: at most {per_image} patterns of {bit_depth} bit(s) fit in one image, got {n}")
    if patterns.dtype == np.bool_:
        values = patterns.view(np.uint8)
    else:
        if not np.issubdtype(patterns.dtype, np.integer):
            raise ValueError(f"patterns: expected bool or integer dtype, got {patterns.dtype}")
        if patterns.size and (patterns.min() < 0 or patterns.max() >= (1 << bit_depth)):
            raise ValueError(f"patterns: values must lie in [0, {1 << bit_depth}) for bit_depth={bit_depth}")
        values = patterns.astype(np.uint8, copy=False)
    h, w = values.shape[1:]
    planes = np.zeros((3, h, w), dtype=np.uint8)  # bytes 0..2 of every pixel
    for k in range(n):  # at most 24 whole-array operations on uint8
        for b in range(bit_depth):
            pos = k * bit_depth + b
            bit = values[k] if bit_depth == 1 else (values[k] >> b) & 1
            planes[pos // 8] |= bit << np.uint8(pos % 8)
    return (planes[0].astype(np.uint32) | (planes[1].astype(np.uint32) << 8)
            | (planes[2].astype(np.uint32) << 16))


def _wire_bytes(px: np.ndarray) -> np.ndarray:
    """(N, 3) bytes of 24-bit pixels (little-endian uint32 input) in wire order: bits 23-16,
    15-8, then 7-0."""
    return px.view(np.uint8).reshape(-1, 4)[:, 2::-1]


def _count_bytes(n: np.ndarray) -> np.ndarray:
    return np.where(n < 128, 1, 2)


def _put_counts(out: np.ndarray, at: np.ndarray, n: np.ndarray) -> None:
    small = n < 128
    out[at[small]] = n[small]
    big_at, big = at[~small], n[~small]
    out[big_at] = (big & 0x7F) | 0x80
    out[big_at + 1] = big >> 7


def erle_encode(image: np.ndarray) -> bytes:
    """Enhanced-RLE payload of a (H, W) 24-bit image (uint32), ending with the end-of-image code.

    A line equal to the one above becomes one copy token; other lines become repeat tokens for
    runs and uncompressed blocks for stretches of single pixels. Every line ends with 00 00.
    """
    px = np.ascontiguousarray(image)
    if px.ndim != 2 or not np.issubdtype(px.dtype, np.integer):
        raise ValueError(f"image: expected a (H, W) integer array, got {px.shape} {px.dtype}")
    if px.size == 0:
        raise ValueError("image: empty")
    if px.min() < 0 or px.max() >= (1 << 24):
        raise ValueError("image: pixel values must fit in 24 bits")
    h, w = px.shape
    if w > MAX_COUNT:
        raise ValueError(f"image: width {w} exceeds the encodable count {MAX_COUNT}")
    px = px.astype("<u4", copy=False)
    pix_bytes = _wire_bytes(px)  # (H*W, 3)

    copy_row = np.zeros(h, dtype=bool)
    copy_row[1:] = np.all(px[1:] == px[:-1], axis=1)
    enc_rows = np.flatnonzero(~copy_row)
    sub = px[enc_rows]
    r = len(enc_rows)

    change = np.ones((r, w), dtype=bool)
    change[:, 1:] = sub[:, 1:] != sub[:, :-1]
    starts = np.flatnonzero(change)  # flat index into sub; a run never spans lines
    lengths = np.diff(np.append(starts, r * w))
    run_line = starts // w
    single = lengths == 1
    prev_single = np.zeros_like(single)
    prev_single[1:] = single[:-1] & (run_line[1:] == run_line[:-1])
    group_start = single & ~prev_single
    group_id = np.cumsum(group_start) - 1
    group_size = np.bincount(group_id[single], minlength=int(group_start.sum()))
    # Runs that are not singles, and single groups of size one, become repeat tokens.
    in_literal = np.zeros_like(single)
    in_literal[single] = group_size[group_id[single]] >= 2
    rep = ~in_literal
    lit_first = group_start & in_literal
    lit_n = group_size[group_id[lit_first]]
    # No token needs splitting: runs and literals stay within a line, and w <= MAX_COUNT.
    # Tokens: kind 0 repeat, 1 literal, 2 copy, 3 end of line. Sorted by (row, position).
    src_row_of = enc_rows  # sub line -> image row
    rep_pos = starts[rep]
    lit_pos = starts[lit_first]
    rows = np.concatenate([src_row_of[rep_pos // w], src_row_of[lit_pos // w],
                           np.flatnonzero(copy_row), np.arange(h)])
    cols = np.concatenate([rep_pos % w, lit_pos % w, np.zeros(int(copy_row.sum()), np.int64),
                           np.full(h, w, np.int64)])
    kind = np.concatenate([np.zeros(len(rep_pos), np.int8), np.ones(len(lit_pos), np.int8),
                           np.full(int(copy_row.sum()), 2, np.int8), np.full(h, 3, np.int8)])
    count = np.concatenate([lengths[rep], lit_n, np.full(int(copy_row.sum()), w, np.int64),
                            np.zeros(h, np.int64)])
    order = np.argsort(rows.astype(np.int64) * (w + 1) + cols, kind="stable")
    rows, cols, kind, count = rows[order], cols[order], kind[order], count[order]

    cb = _count_bytes(count)
    size = np.select([kind == 0, kind == 1, kind == 2], [cb + 3, 1 + cb + 3 * count, 2 + cb], 2)
    offset = np.zeros(len(size) + 1, dtype=np.int64)
    np.cumsum(size, out=offset[1:])
    out = np.zeros(int(offset[-1]) + 3, dtype=np.uint8)
    out[-2] = 1  # 00 01 00: end of image
    off = offset[:-1]
    src = rows.astype(np.int64) * w + cols  # flat pixel index of each token's first pixel

    m = kind == 0
    _put_counts(out, off[m], count[m])
    dst = off[m] + cb[m]
    out[dst[:, None] + np.arange(3)] = pix_bytes[src[m]]

    m = kind == 1
    _put_counts(out, off[m] + 1, count[m])
    n = count[m]
    first_dst = off[m] + 1 + cb[m]
    tok = np.repeat(np.arange(len(n)), n)
    k = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)
    dst = first_dst[tok] + 3 * k
    out[dst[:, None] + np.arange(3)] = pix_bytes[src[m][tok] + k]

    m = kind == 2
    out[off[m] + 1] = 1
    _put_counts(out, off[m] + 2, count[m])
    return out.tobytes()


def raw_encode(image: np.ndarray) -> bytes:
    """Uncompressed payload (compression 0): three bytes per pixel, most significant first, row-major."""
    return _wire_bytes(np.ascontiguousarray(image).astype("<u4", copy=False)).tobytes()


def encode_image(image: np.ndarray, compression: int | str = "auto",
                 background_bgr: tuple[int, int, int] = (0, 0, 0)) -> EncodedImage:
    """Header + payload for one 24-bit (H, W) image, ready for 0x1A2A/0x1A2B.

    "auto" sends enhanced RLE unless it comes out larger than the raw pixels (random
    patterns), in which case the image goes uncompressed: fewer bytes over USB either way.
    """
    image = np.asarray(image)
    if image.ndim != 2:
        raise ValueError(f"image: expected (H, W), got {image.shape}")
    h, w = image.shape
    if compression in ("auto", COMPRESSION_ERLE):
        payload = erle_encode(image)
        chosen = COMPRESSION_ERLE
        if compression == "auto" and len(payload) > 3 * h * w:
            payload, chosen = raw_encode(image), COMPRESSION_NONE
    elif compression == COMPRESSION_NONE:
        payload, chosen = raw_encode(image), COMPRESSION_NONE
    else:
        raise ValueError(f"compression: expected 'auto', 0 (none) or 2 (enhanced RLE), got {compression!r}")
    return EncodedImage(w, h, chosen, image_header(w, h, len(payload), chosen, background_bgr) + payload)
