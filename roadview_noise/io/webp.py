"""WebP camera files: the RIFF container (Google, "WebP Container Specification") read and written here; the pixels
are decoded and encoded by OpenCV's libwebp in :mod:`.image`.

- A still image: a lossy ``VP8 `` bitstream (RFC 6386) or a lossless ``VP8L`` one, 8-bit sRGB, with an alpha plane
  (``ALPH`` chunk, or VP8L's own). An animation (``ANIM``/``ANMF`` chunks, VP8X animation flag) is refused.
- Written back like the input: lossless stays lossless (libwebp without its exact mode: the colour of a pixel with
  alpha 0 may change, which no viewer shows); lossy at the input's quality, estimated from the VP8 frame header
  (:func:`vp8_quality`); the ``ICCP``, ``EXIF`` (orientation included: the pixels are read and written as stored)
  and ``XMP `` chunks copied unchanged into an extended (``VP8X``) container.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError

SIGNATURE = b"RIFF", b"WEBP"
_IMAGE = (b"ALPH", b"VP8 ", b"VP8L")
_ANIMATION = (b"ANIM", b"ANMF")
_FLAG_ICC, _FLAG_ALPHA, _FLAG_EXIF, _FLAG_XMP, _FLAG_ANIMATION = 0x20, 0x10, 0x08, 0x04, 0x02
# libwebp's segment quantiser spread (src/enc/quant_enc.c): SNS_TO_DQ 0.9 × the default sns_strength 50 / 100 / 128,
# at the most-quantised segment's alpha −127
_SNS_AMPLITUDE = 0.9 * 50 / 100 / 128
_HARDEST_SEGMENT_EXPONENT = 1 + _SNS_AMPLITUDE * 127


def is_webp(data: bytes) -> bool:
    return data[:4] == SIGNATURE[0] and data[8:12] == SIGNATURE[1]


def _spans(data: bytes):
    """``(fourcc, payload offset, declared payload size)`` of the container's chunks, in file order (each padded to
    an even size)."""
    pos = 12
    while pos + 8 <= len(data):
        size = int.from_bytes(data[pos + 4:pos + 8], "little")
        yield data[pos:pos + 4], pos + 8, size
        pos += 8 + size + (size & 1)


def chunks(data: bytes) -> list[tuple[bytes, bytes]]:
    """``(fourcc, payload)`` of the container's chunks, in file order."""
    return [(kind, data[start:start + size]) for kind, start, size in _spans(data)]


def check_structure(data: bytes, path) -> None:
    """InputError naming the file for what is not a still WebP image or is cut short."""
    if not is_webp(data):
        raise InputError("not a WebP file (no RIFF … WEBP header)", file=str(path))
    declared = int.from_bytes(data[4:8], "little") + 8
    spans = list(_spans(data))
    if len(data) < declared or any(start + size > len(data) for _, start, size in spans):
        raise InputError(f"truncated WebP: the RIFF header gives {declared} bytes, the file has {len(data)}",
                         file=str(path))
    kinds = [kind for kind, _, _ in spans]
    extended = dict(chunks(data)).get(b"VP8X", b"\x00")
    if any(k in _ANIMATION for k in kinds) or extended[0] & _FLAG_ANIMATION:
        raise InputError("an animated WebP: rvnoise augments one still image per file; extract the frames first "
                         "(webpmux -get frame N, or ffmpeg)", file=str(path))
    if not any(k in (b"VP8 ", b"VP8L") for k in kinds):
        raise InputError("a WebP file without an image bitstream (VP8 or VP8L chunk)", file=str(path))


def metadata(data: bytes) -> tuple[bytes | None, bytes | None, tuple[bytes, ...]]:
    """``(ICC profile, EXIF, XMP chunks whole)`` of a WebP file, as stored (an EXIF chunk may start with the
    ``Exif\\0\\0`` header some writers put before the TIFF structure: kept)."""
    parts = chunks(data)
    icc = next((body for kind, body in parts if kind == b"ICCP"), None)
    exif = next((body for kind, body in parts if kind == b"EXIF"), None)
    xmp = tuple(_chunk(kind, body) for kind, body in parts if kind == b"XMP ")
    return icc or None, exif or None, xmp


def quality(data: bytes) -> int | None:
    """None for a lossless file, else the lossy quality (1–100) :func:`vp8_quality` estimates."""
    vp8 = dict(chunks(data)).get(b"VP8 ")
    return None if vp8 is None else vp8_quality(vp8)


def vp8_quality(vp8: bytes) -> int:
    """The libwebp quality (cwebp ``-q``, OpenCV ``IMWRITE_WEBP_QUALITY``, Pillow ``quality``) a VP8 key frame was
    encoded at, from its quantiser indices (RFC 6386 §9.3, §9.6): libwebp sets segment i's index to
    127·(1 − c^(1 − a·α_i)), c = (linear quality)^(1/3) (quant_enc.c ``QualityToCompression``), α_i ∈ [−127, 127]
    its segment's complexity (analysis_enc.c), a = 0.9 · sns 50 / 100 / 128; the most-quantised segment is taken at
    α = −127, all segments at one index as no noise shaping. libwebp's default noise shaping (sns 50: OpenCV's,
    Pillow's and cwebp's default) is assumed; another ``-sns`` is not modelled. On 448 encodes by libwebp (7
    photos at two sizes, qualities 5–98, segmentation on) the estimate is within ±1 of the quality for 90 % of
    them, within ±5 for all."""
    indices = _vp8_quantiser_indices(vp8)
    spread = max(indices) != min(indices)           # segments of one index: no noise shaping (sns 0)
    c = (1 - (max(indices) + 0.5) / 127) ** (1 / (_HARDEST_SEGMENT_EXPONENT if spread else 1))
    linear = c ** 3
    q = linear * 1.5 if linear < 0.5 else (linear + 1) / 2
    return int(np.clip(np.rint(100 * q), 1, 100))


def _vp8_quantiser_indices(vp8: bytes) -> list[int]:
    """The luma AC quantiser index of each segment of a VP8 key frame (one without segmentation), read from its
    first partition (RFC 6386 §9.2–9.6, §19.2) with the boolean decoder of §7."""
    bits = _BoolDecoder(vp8[10:])                    # after the 3-byte frame tag, start code and dimensions
    bits.literal(2)                                  # colour space, clamping type
    segment_q, absolute = None, True
    if bits.literal(1):                              # segmentation enabled
        update_map, update_data = bits.literal(1), bits.literal(1)
        if update_data:
            absolute = bits.literal(1)
            segment_q = [bits.signed(7) if bits.literal(1) else 0 for _ in range(4)]
            for _ in range(4):                       # loop filter levels
                if bits.literal(1):
                    bits.signed(6)
        if update_map:
            for _ in range(3):
                if bits.literal(1):
                    bits.literal(8)
    bits.literal(10)                                 # filter type, level, sharpness
    if bits.literal(1) and bits.literal(1):          # loop filter deltas, updated
        for _ in range(8):
            if bits.literal(1):
                bits.signed(6)
    bits.literal(2)                                  # DCT partitions
    base = bits.literal(7)
    if segment_q is None:
        return [base]
    return [q if absolute else base + q for q in segment_q]


class _BoolDecoder:
    """RFC 6386 §7.3's boolean entropy decoder, for the few header fields read (literals at probability ½)."""

    def __init__(self, data: bytes):
        self.data, self.pos = data, 2
        self.value, self.range, self.count = int.from_bytes(data[:2], "big"), 255, 0

    def bit(self) -> int:
        split = 1 + ((self.range - 1) * 128 >> 8)
        high = split << 8
        if self.value >= high:
            bit, self.range, self.value = 1, self.range - split, self.value - high
        else:
            bit, self.range = 0, split
        while self.range < 128:
            self.value, self.range, self.count = (self.value << 1) & 0xFFFF, self.range << 1, self.count + 1
            if self.count == 8:
                self.count = 0
                self.value |= self.data[self.pos] if self.pos < len(self.data) else 0
                self.pos += 1
        return bit

    def literal(self, n: int) -> int:
        value = 0
        for _ in range(n):
            value = value << 1 | self.bit()
        return value

    def signed(self, n: int) -> int:
        value = self.literal(n)
        return -value if self.bit() else value


def with_metadata(encoded: bytes, width: int, height: int, icc: bytes | None, exif: bytes | None,
                  xmp: tuple[bytes, ...] = ()) -> bytes:
    """A WebP file libwebp wrote (simple or extended container) with ``icc``, ``exif`` and the whole ``xmp`` chunks
    in an extended container: VP8X, ICCP, the image chunks, EXIF, XMP (the specification's order); the input
    bytes when there is nothing to add."""
    if not (icc or exif or xmp):
        return encoded
    image = [(kind, body) for kind, body in chunks(encoded) if kind in _IMAGE]
    alpha = any(kind == b"ALPH" for kind, _ in image) or any(
        kind == b"VP8L" and int.from_bytes(body[1:5], "little") >> 28 & 1 for kind, body in image)
    flags = (_FLAG_ICC if icc else 0) | (_FLAG_ALPHA if alpha else 0) | (_FLAG_EXIF if exif else 0) | \
        (_FLAG_XMP if xmp else 0)
    vp8x = bytes([flags, 0, 0, 0]) + (width - 1).to_bytes(3, "little") + (height - 1).to_bytes(3, "little")
    body = _chunk(b"VP8X", vp8x) + (_chunk(b"ICCP", icc) if icc else b"") + \
        b"".join(_chunk(kind, payload) for kind, payload in image) + (_chunk(b"EXIF", exif) if exif else b"") + \
        b"".join(xmp)
    return b"RIFF" + (len(body) + 4).to_bytes(4, "little") + b"WEBP" + body


def _chunk(kind: bytes, payload: bytes) -> bytes:
    return kind + len(payload).to_bytes(4, "little") + payload + b"\x00" * (len(payload) & 1)
