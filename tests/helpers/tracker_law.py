"""Simulated data with a real tracker's noise: a constant plus a part growing with range,
larger across the beam than along it (docs/physics.md). The noise is drawn here, in the
test, from the law written out in numpy (not with the code under test): the simulator
gives noise-free readings and this adds ``sigma(R) = a + b R`` along the beam (the
direction from the head, the origin of the tracker's frame) and across it."""

from dataclasses import replace

import numpy as np

#: a laser tracker's statement U = a + b R (k = 2), as sigma [m, m/m]: the distance meter along
#: the beam, the angle encoders across it (15 µm + 6 µm/m across, a third of it along)
ALONG = (2.5e-6, 1.0e-6)
ACROSS = (7.5e-6, 3.0e-6)


def add_tracker_noise(table, seed: int, along=ALONG, across=ACROSS):
    """The table with each reading moved by the law's noise (its own generator)."""
    rng = np.random.default_rng(10_000 + seed)
    p = np.asarray(table.xyz, dtype=float)
    r = np.linalg.norm(p, axis=1)
    u = p / r[:, None]
    # two directions across the beam
    a = np.where(np.abs(u[:, 2:3]) < 0.9, np.array([[0.0, 0.0, 1.0]]), np.array([[1.0, 0.0, 0.0]]))
    v = np.cross(u, a)
    v /= np.linalg.norm(v, axis=1)[:, None]
    w = np.cross(u, v)
    s_al = along[0] + along[1] * r
    s_ac = across[0] + across[1] * r
    z = rng.standard_normal((len(p), 3))
    noisy = p + u * (s_al * z[:, 0])[:, None] + v * (s_ac * z[:, 1])[:, None] + w * (s_ac * z[:, 2])[:, None]
    return replace(table, xyz=noisy)
