"""Seeded byte-level mutants of a valid file, for the readers' fuzz tests: bytes replaced, runs
cut out, bytes put in."""

from __future__ import annotations

import random
from collections.abc import Callable, Iterator
from pathlib import Path


def byte_mutants(
    base: bytes,
    seed: int,
    count: int,
    *,
    edits: int = 5,
    cut: int = 30,
    put: bytes | None = None,
) -> Iterator[bytes]:
    """``count`` mutants of ``base``, each with 1 to ``edits`` edits: a byte replaced, up to
    ``cut`` bytes cut out, or 1 to 5 bytes put in; replaced and put bytes drawn from ``put``
    (default: any byte)."""
    rng = random.Random(seed)

    def byte() -> int:
        return rng.choice(put) if put else rng.randrange(256)

    for _ in range(count):
        b = bytearray(base)
        for _ in range(rng.randint(1, edits)):
            k = rng.randrange(len(b))
            r = rng.random()
            if r < 0.45:
                b[k] = byte()
            elif r < 0.8:
                del b[k : k + rng.randint(1, cut)]
            else:
                b[k:k] = bytes(byte() for _ in range(rng.randint(1, 5)))
        yield bytes(b)


def read_or_refused(
    mutants: Iterator[bytes], path: Path, read: Callable[[Path], object], refused: type[Exception]
) -> dict[str, int]:
    """Write each mutant to ``path`` and read it: counts of reads and refusals (``refused``);
    any other exception propagates (the test fails on it)."""
    seen = {"read": 0, "refused": 0}
    for m in mutants:
        path.write_bytes(m)
        try:
            read(path)
            seen["read"] += 1
        except refused:
            seen["refused"] += 1
    return seen
