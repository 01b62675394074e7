"""What the training tests share: the options of a tiny ``cva-train`` run (a second or two)."""

from __future__ import annotations

#: Two 24×40 synthetic pairs at D = 16, 32 samples an epoch, one thread, no progress bar.
TINY = [
    '--matcher', 'census_bm',
    '--max-disparity', '16',
    '--synthetic', '2',
    '--synthetic-size', '24x40',
    '--val-synthetic', '1',
    '--val-pixels', '40',
    '--batch-size', '16',
    '--samples-per-epoch', '32',
    '--seed', '7',
    '--threads', '1',
    '--no-progress',
]  # fmt: skip
