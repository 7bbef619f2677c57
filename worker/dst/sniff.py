"""Recognising a STEP file from its first bytes (no OCCT: the API checks uploads with it)."""

from __future__ import annotations

SNIFF_BYTES = 256  # enough for a byte-order mark, whitespace and the Part 21 magic
_P21_MAGIC = b"ISO-10303-21"


def sniff_step(head: bytes) -> bool:
    """True if ``head`` (the first bytes of a file) starts like an ISO 10303-21 file."""
    return head.lstrip(b"\xef\xbb\xbf \t\r\n").upper().startswith(_P21_MAGIC)
