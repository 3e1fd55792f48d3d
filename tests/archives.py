"""Byte-level helpers the hostile-input and fuzz tests share: zip archives, mutations."""

from __future__ import annotations

import io
import zipfile

import numpy as np


def zip_bytes(members: dict[str, bytes], compression: int = zipfile.ZIP_STORED) -> bytes:
    """A zip archive (an ``.npz`` when the members are ``.npy`` files) of ``members``."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression) as z:
        for name, data in members.items():
            z.writestr(name, data)
    return buf.getvalue()


def flip_bytes(rng: np.random.Generator, data: bytes) -> tuple[bytes, str]:
    """1 to 16 random bytes of ``data`` XOR-ed with a random non-zero value."""
    raw = bytearray(data)
    n = int(rng.integers(1, 17))
    for i in rng.integers(0, len(raw), n):
        raw[i] ^= int(rng.integers(1, 256))
    return bytes(raw), f"{n} bytes flipped"


def truncate_bytes(rng: np.random.Generator, data: bytes) -> tuple[bytes, str]:
    """``data`` cut at a random length."""
    n = int(rng.integers(0, len(data)))
    return data[:n], f"cut at {n} of {len(data)} bytes"
