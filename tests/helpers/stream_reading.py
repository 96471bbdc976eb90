"""Reading a stream by count, not by duration: what the device tests use under load.

``stream.read_for(0.5)`` then "at least 70 samples" asserts how fast the machine ran: a
loaded machine delivers fewer in the same half second. :func:`read_samples` reads until
the stream delivered what the test needs (each read waits up to ``timeout_s`` for data);
a loaded machine only makes it take longer. ``max_reads`` only ends a hang.
"""

from __future__ import annotations

from typing import Callable

from elastocal.drivers.samples import Batch


def read_samples(stream, n: int | None = None, *, until: Callable[[list], bool] | None = None,
                 timeout_s: float = 1.0, max_reads: int = 2000) -> Batch:
    """Samples and gaps read until there are ``n`` samples (or ``until(samples)`` holds)."""
    if (n is None) == (until is None):
        raise ValueError("give n or until")
    done = until if until is not None else (lambda samples: len(samples) >= n)
    samples: list = []
    gaps: list = []
    for _ in range(max_reads):
        batch = stream.read(timeout_s=timeout_s)
        samples += batch.samples
        gaps += batch.gaps
        if done(samples):
            return Batch(tuple(samples), tuple(gaps))
    raise AssertionError(f"the stream delivered {len(samples)} samples in {max_reads} reads")
