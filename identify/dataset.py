"""A static table reduced to load states and deflections (:class:`StaticDataset`).

:func:`build_dataset` averages a validated table's repeated readings per (pose, load)
state and marker, forms every loaded state's deflections against its pose's reference,
and estimates the noise: the tracker's repeatability (readings far off their repeats left
out, identify/outliers.py) or its noise law, and the currents'.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from elastocal.errors import InputError
from elastocal.formats.tables import StaticTable
from elastocal.identify.grouping import combine, first_seen, group_count, group_sum, sums_per_group
from elastocal.model.kinds import NoiseSource
from elastocal.model.tracker_noise import TrackerNoise


@dataclass(frozen=True, eq=False)
class StaticDataset:
    """A static table reduced to load states and deflections.

    States ``s`` are (pose, load) pairs; deflections ``d`` are (loaded state,
    marker) pairs, measured against the reference state of the same pose.
    """

    source: str
    pose_ids: tuple[str, ...]
    q: np.ndarray                 # (P, N)
    markers: tuple[str, ...]
    state_pose: np.ndarray        # (S,) index into pose_ids
    state_load: np.ndarray        # (S,) str
    state_ref: np.ndarray         # (S,) index of the pose's reference state
    state_currents: np.ndarray    # (S, N) mean currents [A], NaN when absent
    state_n_currents: np.ndarray  # (S,) distinct drive readings averaged (docs/formats.md §2)
    state_wrench: np.ndarray      # (S, 6) [N, N·m], NaN when unknown; 0 for references without one
    defl_state: np.ndarray        # (D,)
    defl_ref: np.ndarray          # (D,)
    defl_marker: np.ndarray       # (D,) index into markers
    dP: np.ndarray                # (D, 3) measured deflection [m]
    defl_n: np.ndarray            # (D,) readings averaged in the loaded state
    defl_n_ref: np.ndarray        # (D,) readings averaged in the reference
    defl_dt: np.ndarray           # (D,) mean time loaded minus mean time reference [s], NaN if unknown
    defl_t: np.ndarray            # (D,) mean time of the loaded readings [s], NaN if unknown
    sigma_tracker: float | None   # repeatability per coordinate [m]
    sigma_current: np.ndarray | None  # (N,) repeatability per joint [A]
    #: tracker readings far off their repeats (identify/outliers.py): left out of
    #: sigma_tracker; in the means unless the table was refitted without them
    outliers: tuple = ()
    #: (D,) variance per coordinate of each deflection from the readings' U95 (the optional
    #: ``u95`` column, docs/import.md; sigma = U95 / 1.96), None without it: the fit's weights
    defl_u95_var: np.ndarray | None = None
    #: (D,) the part of it from the reference state's readings (shared by the deflections of a marker)
    defl_u95_var_ref: np.ndarray | None = None
    abs_xyz: np.ndarray | None = None  # (S, M, 3) mean absolute position per state and marker, tracker frame [m]
    abs_n: np.ndarray | None = None    # (S, M) readings averaged
    abs_t: np.ndarray | None = None    # (S, M) mean time of those readings [s], NaN if unknown
    #: (S, M, 3) variance per coordinate of those mean readings from the readings' own stated
    #: uncertainty (``u95`` or ``sx, sy, sz``), None without it [m²]
    abs_var: np.ndarray | None = None
    #: rotation tracker <- base that dP was turned back by (identify/registration.py); None: dP as measured
    tracker_rotation: np.ndarray | None = None
    #: the tracker's noise law in force (model/tracker_noise.py): estimated from the repeats where
    #: they are enough, else the cell's; None without either
    tracker_noise: TrackerNoise | None = None
    #: (S, M, 3, 3) covariance of each state's mean reading of each marker under that law,
    #: tracker frame [m²]; None without a law
    abs_cov: np.ndarray | None = None
    #: where the noise level comes from (repeats, the uncertainty columns, a law, none); None:
    #: from the fields (repeats when ``sigma_tracker`` is set, else the columns when ``abs_var`` is)
    noise_source: NoiseSource | None = None

    def __post_init__(self) -> None:
        if self.noise_source is None:
            object.__setattr__(self, "noise_source", NoiseSource.REPEATS if self.sigma_tracker is not None else
                               NoiseSource.UNCERTAINTY_COLUMNS if self.abs_var is not None else NoiseSource.NONE)

    @property
    def n_states(self) -> int:
        return len(self.state_pose)

    @property
    def n_deflections(self) -> int:
        return len(self.defl_state)

    @property
    def has_currents(self) -> bool:
        return bool(np.all(np.isfinite(self.state_currents)))

    @property
    def has_wrench(self) -> bool:
        return bool(np.all(np.isfinite(self.state_wrench)))


def distinct_readings(currents: np.ndarray) -> np.ndarray:
    """The distinct drive readings among a load state's rows (docs/formats.md §2):
    rows that carry identical currents share one reading (the currents of one
    repeat read once for all its markers), which counts once in the mean and
    in the noise estimate. Order of first appearance is kept."""
    if len(currents) < 2 or not np.all(np.isfinite(currents)):
        return currents
    _, first = np.unique(currents, axis=0, return_index=True)
    return currents[np.sort(first)]


def _in_order(values: np.ndarray, start: np.ndarray | float) -> np.ndarray:
    """``start`` plus the ``values`` (along axis 0) added one after the other, in order: the sum
    a loop over the groups makes, to the last bit (the fits downstream are that sensitive)."""
    return np.add.accumulate(np.concatenate([np.asarray(start, dtype=float)[None], values]), axis=0)[-1]


def build_dataset(table: StaticTable, *, tracker_noise: TrackerNoise | None = None) -> StaticDataset:
    """Average repeated readings and form the deflections of a validated table.

    The tracker's repeatability leaves out the readings far off their repeats
    (identify/outliers.py); they are listed in ``outliers``. The tracker's noise
    law (identify/trackernoise.py) is estimated from the repeats where they are
    enough, else ``tracker_noise`` (cell.toml ``[tracker] noise``) is taken; it gives
    every mean reading its covariance (``abs_cov``) and, without repeats, the noise level.

    States are numbered pose by pose in order of first appearance, the reference (load 0)
    first, then the pose's loads in order of first appearance; deflections run over the
    loaded states and every marker of the table. One grouped pass over the rows
    (identify/grouping.py): no Python loop per row, state or marker."""
    from elastocal.identify.outliers import find_outliers, outlier_mask, tracker_noise_of

    stated_law = tracker_noise if tracker_noise is not None else table.tracker_noise
    noise = tracker_noise_of(table, stated_law)
    outliers = find_outliers(table, noise=noise)
    bad = outlier_mask(len(table), outliers)
    pose_code, pose_first = first_seen(table.pose)
    marker_code, marker_first = first_seen(table.marker)
    pose_ids = tuple(table.pose[pose_first])
    markers = tuple(table.marker[marker_first])
    q = table.q[pose_first]
    n_markers = len(markers)
    missing = sorted(set(range(len(pose_ids))) - set(pose_code[table.load == "0"].tolist()))
    if missing:
        p = pose_ids[missing[0]]
        raise InputError(f"pose {p} has no unloaded reference (load 0)", source=table.source,
                         row=int(table.line[pose_first[missing[0]]]), column="load")

    # states: (pose, load) pairs, the reference first within a pose, then in order of first appearance
    pair_code, pair_first = first_seen(combine(pose_code, first_seen(table.load)[0]))
    order = np.lexsort((pair_first, table.load[pair_first] != "0", pose_code[pair_first]))
    state_of_pair = np.empty(len(order), dtype=np.intp)
    state_of_pair[order] = np.arange(len(order))
    state = state_of_pair[pair_code]                       # (n,) state of each row
    first_row = pair_first[order]                          # (S,) first row of each state
    n_states = len(first_row)
    state_pose = pose_code[first_row]
    state_load = np.array(list(table.load[first_row]), dtype=str)
    state_ref = np.searchsorted(state_pose, state_pose)    # states are sorted by pose, reference first

    # currents: the distinct drive readings of each state (distinct_readings), averaged
    currents = table.currents
    row_finite = np.all(np.isfinite(currents), axis=1)
    state_finite = group_count(state[~row_finite], n_states) == 0
    keep = np.ones(len(table), dtype=bool)
    dedupe = np.flatnonzero(state_finite[state])
    if dedupe.size:
        _, first = np.unique(np.column_stack([state[dedupe].astype(float), currents[dedupe]]), axis=0,
                             return_index=True)
        keep[dedupe] = False
        keep[dedupe[first]] = True
    ncur = group_count(state[keep], n_states)
    with np.errstate(invalid="ignore", divide="ignore"):
        cur = group_sum(state[keep], currents[keep], n_states) / ncur[:, None]
    noisy = state_finite & (ncur > 1)
    rows_i = keep & noisy[state]
    per_state = group_sum(state[rows_i], (currents[rows_i] - cur[state[rows_i]]) ** 2, n_states)[noisy]
    dev_sq_i = _in_order(per_state, np.zeros(table.n_joints))
    dof_i = int(np.sum(ncur[noisy] - 1))

    wrench = table.wrench[first_row].copy()
    blank_ref = (state_load == "0") & ~np.all(np.isfinite(wrench), axis=1)
    wrench[blank_ref] = 0.0

    # (state, marker) cells: mean position, readings, mean time; repeatability from the good readings
    cell = state * n_markers + marker_code
    n_cells = n_states * n_markers
    count = group_count(cell, n_cells)
    good = ~bad
    n_good = group_count(cell[good], n_cells)
    with np.errstate(invalid="ignore", divide="ignore"):
        xyz_mean = group_sum(cell, table.xyz, n_cells) / count[:, None]
        t_mean = group_sum(cell, table.t, n_cells) / count
        good_mean = group_sum(cell[good], table.xyz[good], n_cells) / n_good[:, None]
    rows_p = np.flatnonzero(good & (n_good[cell] > 1))
    rows_p = rows_p[np.argsort(cell[rows_p], kind="stable")]
    dev_sq_p = float(_in_order(sums_per_group((table.xyz[rows_p] - good_mean[cell[rows_p]]) ** 2,
                                               n_good[n_good > 1]), 0.0))
    dof_p = int(np.sum(3 * (n_good[n_good > 1] - 1)))
    u95 = table.optional("u95")
    if u95 is not None and not (np.all(np.isfinite(u95)) and np.all(u95 > 0)):
        u95 = None                  # weights only when every reading has its uncertainty
    if u95 is not None:             # variance of the mean of the state's readings
        with np.errstate(invalid="ignore", divide="ignore"):
            var_of = group_sum(cell, (u95 / 1.96) ** 2, n_cells) / count.astype(float) ** 2
    abs_var = _reading_variances(table, cell, count, n_cells)

    # deflections: every loaded state against its pose's reference, marker by marker
    loaded = np.flatnonzero(state_ref != np.arange(n_states))
    d_state = np.repeat(loaded, n_markers)
    d_marker = np.tile(np.arange(n_markers), len(loaded))
    d_ref = state_ref[d_state]
    c1, c0 = d_state * n_markers + d_marker, d_ref * n_markers + d_marker
    sigma_tracker = float(np.sqrt(dev_sq_p / dof_p)) if dof_p else None
    sigma_current = np.sqrt(dev_sq_i / dof_i) if dof_i else None
    # the noise level: the repeats, else the readings' own uncertainty, else the law (docs/cli.md)
    source = (NoiseSource.REPEATS if sigma_tracker is not None else
              NoiseSource.UNCERTAINTY_COLUMNS if abs_var is not None else
              NoiseSource.TRACKER_LAW if noise is not None else NoiseSource.NONE)
    abs_cov = None
    if noise is not None:          # each mean reading's covariance under the law
        finite = np.all(np.isfinite(xyz_mean), axis=1)
        if source is NoiseSource.REPEATS and noise is stated_law:
            noise = _at_repeats_level(noise, xyz_mean[finite & (n_good > 1)], sigma_tracker)
        abs_cov = np.full((n_cells, 3, 3), np.nan)
        abs_cov[finite] = noise.covariance(xyz_mean[finite]) / count[finite][:, None, None]
        abs_cov = abs_cov.reshape(n_states, n_markers, 3, 3)
        if source is NoiseSource.TRACKER_LAW:  # no repeats, no stated uncertainty: the law sets the level
            sigma_tracker = noise.rms_sigma(xyz_mean[finite])
    return StaticDataset(
        source=table.source, pose_ids=pose_ids, q=q, markers=markers,
        state_pose=state_pose, state_load=state_load, state_ref=state_ref, state_currents=cur,
        state_n_currents=ncur, state_wrench=wrench, defl_state=d_state, defl_ref=d_ref,
        defl_marker=d_marker, dP=(xyz_mean[c1] - xyz_mean[c0]).reshape(-1, 3),
        defl_n=count[c1], defl_n_ref=count[c0], defl_dt=t_mean[c1] - t_mean[c0],
        defl_t=t_mean[c1], sigma_tracker=sigma_tracker, sigma_current=sigma_current,
        defl_u95_var=var_of[c1] + var_of[c0] if u95 is not None else None,
        defl_u95_var_ref=var_of[c0] if u95 is not None else None,
        outliers=outliers,
        abs_xyz=xyz_mean.reshape(n_states, n_markers, 3), abs_n=count.reshape(n_states, n_markers),
        abs_t=t_mean.reshape(n_states, n_markers).astype(float),
        tracker_noise=noise, abs_cov=abs_cov,
        abs_var=None if abs_var is None else abs_var.reshape(n_states, n_markers, 3), noise_source=source,
    )


def _at_repeats_level(law: TrackerNoise, repeated_xyz: np.ndarray, sigma: float) -> TrackerNoise:
    """A law the cell states, where the table's repeats are too few to estimate one: its shape
    (along and across the beam, over range) with the level of the repeats, which come first."""
    if not len(repeated_xyz):
        return law
    level = law.rms_sigma(repeated_xyz)
    return law.scaled(sigma / level, source=f"{law.source}, scaled to the repeats' level") if level > 0 else law


def _reading_variances(table: StaticTable, cell: np.ndarray, count: np.ndarray, n_cells: int) -> np.ndarray | None:
    """(cells, 3) variance per coordinate of each cell's mean reading from the readings' own
    uncertainties (``u95``: sigma = U95 / 1.96 on each coordinate; ``sx, sy, sz``: per axis), or
    None unless every reading states a positive one (docs/formats.md §2)."""
    u95 = table.optional("u95")
    if u95 is not None:
        sigma = np.repeat((u95 / 1.96)[:, None], 3, axis=1)
    elif table.optional("sx") is not None:
        sigma = np.column_stack([table.optional(c) for c in ("sx", "sy", "sz")])
    else:
        return None
    if not (np.all(np.isfinite(sigma)) and np.all(sigma > 0)):
        return None
    with np.errstate(invalid="ignore", divide="ignore"):
        return group_sum(cell, sigma ** 2, n_cells) / count.astype(float)[:, None] ** 2
