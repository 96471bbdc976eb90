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
    #: rotation tracker <- base that dP was turned back by (identify/registration.py); None: dP as measured
    tracker_rotation: np.ndarray | None = None
    #: the tracker's noise law in force (model/tracker_noise.py): estimated from the repeats where
    #: they are enough, else the cell's; None without either
    tracker_noise: TrackerNoise | None = None
    #: (S, M, 3, 3) covariance of each state's mean reading of each marker, tracker frame [m²], from
    #: what ``noise_source`` names: the readings' own uncertainty columns (``u95``: sigma = U95 / 1.96
    #: on each coordinate; ``sx, sy, sz`` per axis; a diagonal), else the tracker's law in force (at
    #: each reading's range and beam); None without either (repeats alone: ``sigma_tracker``)
    reading_cov: np.ndarray | None = None
    #: where the noise level comes from (repeats, the uncertainty columns, a law, none); None:
    #: from the fields (repeats when ``sigma_tracker`` is set, else the columns when ``reading_cov`` is)
    noise_source: NoiseSource | None = None

    def __post_init__(self) -> None:
        if self.noise_source is None:
            object.__setattr__(self, "noise_source", NoiseSource.REPEATS if self.sigma_tracker is not None else
                               NoiseSource.UNCERTAINTY_COLUMNS if self.reading_cov is not None else NoiseSource.NONE)

    @property
    def stated_variance(self) -> np.ndarray | None:
        """(S, M, 3) variance per coordinate of each mean reading from the uncertainty columns [m²],
        when they set the noise (``noise_source``); else None."""
        if self.noise_source is not NoiseSource.UNCERTAINTY_COLUMNS or self.reading_cov is None:
            return None
        return np.diagonal(self.reading_cov, axis1=-2, axis2=-1)

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


@dataclass(frozen=True, eq=False)
class _States:
    """The table's (pose, load) states: numbered pose by pose, the reference first."""

    of_row: np.ndarray            # (n,) state of each row
    first_row: np.ndarray         # (S,) first row of each state
    pose: np.ndarray              # (S,) index into the poses
    load: np.ndarray              # (S,) str
    ref: np.ndarray               # (S,) the pose's reference state

    @property
    def n(self) -> int:
        return len(self.first_row)


@dataclass(frozen=True, eq=False)
class _Currents:
    """Each state's mean of its distinct drive readings, their number, and the spread's sums."""

    mean: np.ndarray              # (S, N) [A], NaN when absent
    n: np.ndarray                 # (S,) distinct readings averaged
    sigma: np.ndarray | None      # (N,) repeatability per joint [A], None without repeats


@dataclass(frozen=True, eq=False)
class _Cells:
    """The (state, marker) cells' mean readings, counts and times, and the tracker's repeatability."""

    count: np.ndarray             # (S*M,) readings averaged
    xyz: np.ndarray               # (S*M, 3) mean position, tracker frame [m]
    t: np.ndarray                 # (S*M,) mean time [s], NaN if unknown
    sigma_tracker: float | None   # from the good readings' repeats, None without repeats
    u95_var: np.ndarray | None    # (S*M,) variance of the mean from the u95 column, None without it
    stated_var: np.ndarray | None  # (S*M, 3) per coordinate, from u95 or sx, sy, sz (_reading_variances)
    repeated: np.ndarray          # (S*M,) bool: cells with more than one good reading


def build_dataset(table: StaticTable, *, tracker_noise: TrackerNoise | None = None) -> StaticDataset:
    """Average repeated readings and form the deflections of a validated table.

    The tracker's repeatability leaves out the readings far off their repeats
    (identify/outliers.py); they are listed in ``outliers``. The tracker's noise
    law (identify/trackernoise.py) is estimated from the repeats where they are
    enough, else ``tracker_noise`` (cell.toml ``[tracker] noise``) is taken; it gives
    every mean reading its covariance (``reading_cov``; the uncertainty columns' when they set the level) and, without repeats, the noise level.

    States are numbered pose by pose in order of first appearance, the reference (load 0)
    first, then the pose's loads in order of first appearance; deflections run over the
    loaded states and every marker of the table. One grouped pass over the rows
    (identify/grouping.py): no Python loop per row, state or marker."""
    from elastocal.identify.outliers import find_outliers, outlier_mask, tracker_noise_of

    stated_law = tracker_noise if tracker_noise is not None else table.tracker_noise
    noise = tracker_noise_of(table, stated_law)
    outliers = find_outliers(table, noise=noise)
    pose_code, pose_first = first_seen(table.pose)
    marker_code, marker_first = first_seen(table.marker)
    pose_ids = tuple(table.pose[pose_first])
    markers = tuple(table.marker[marker_first])
    n_markers = len(markers)
    states = _states(table, pose_code, pose_first, pose_ids)
    currents = _state_currents(table, states)
    wrench = table.wrench[states.first_row].copy()
    blank_ref = (states.load == "0") & ~np.all(np.isfinite(wrench), axis=1)
    wrench[blank_ref] = 0.0
    cells = _cells(table, states.of_row * n_markers + marker_code, states.n * n_markers,
                   ~outlier_mask(len(table), outliers))
    noise, abs_cov, sigma_tracker, source = _noise_level(noise, stated_law, cells, states.n, n_markers)

    # deflections: every loaded state against its pose's reference, marker by marker
    loaded = np.flatnonzero(states.ref != np.arange(states.n))
    d_state = np.repeat(loaded, n_markers)
    d_marker = np.tile(np.arange(n_markers), len(loaded))
    d_ref = states.ref[d_state]
    c1, c0 = d_state * n_markers + d_marker, d_ref * n_markers + d_marker
    var_of = cells.u95_var
    return StaticDataset(
        source=table.source, pose_ids=pose_ids, q=table.q[pose_first], markers=markers,
        state_pose=states.pose, state_load=states.load, state_ref=states.ref, state_currents=currents.mean,
        state_n_currents=currents.n, state_wrench=wrench, defl_state=d_state, defl_ref=d_ref,
        defl_marker=d_marker, dP=(cells.xyz[c1] - cells.xyz[c0]).reshape(-1, 3),
        defl_n=cells.count[c1], defl_n_ref=cells.count[c0], defl_dt=cells.t[c1] - cells.t[c0],
        defl_t=cells.t[c1], sigma_tracker=sigma_tracker, sigma_current=currents.sigma,
        defl_u95_var=var_of[c1] + var_of[c0] if var_of is not None else None,
        defl_u95_var_ref=var_of[c0] if var_of is not None else None,
        outliers=outliers,
        abs_xyz=cells.xyz.reshape(states.n, n_markers, 3), abs_n=cells.count.reshape(states.n, n_markers),
        abs_t=cells.t.reshape(states.n, n_markers).astype(float),
        tracker_noise=noise, noise_source=source,
        reading_cov=_stated_covariance(cells.stated_var, states.n, n_markers)
        if source is NoiseSource.UNCERTAINTY_COLUMNS else abs_cov,
    )


def _states(table: StaticTable, pose_code: np.ndarray, pose_first: np.ndarray, pose_ids: tuple) -> _States:
    """(pose, load) pairs, the reference first within a pose, then in order of first appearance;
    refused when a pose has no unloaded reference."""
    missing = sorted(set(range(len(pose_ids))) - set(pose_code[table.load == "0"].tolist()))
    if missing:
        p = pose_ids[missing[0]]
        raise InputError(f"pose {p} has no unloaded reference (load 0)", source=table.source,
                         row=int(table.line[pose_first[missing[0]]]), column="load")
    pair_code, pair_first = first_seen(combine(pose_code, first_seen(table.load)[0]))
    order = np.lexsort((pair_first, table.load[pair_first] != "0", pose_code[pair_first]))
    state_of_pair = np.empty(len(order), dtype=np.intp)
    state_of_pair[order] = np.arange(len(order))
    first_row = pair_first[order]
    state_pose = pose_code[first_row]
    return _States(of_row=state_of_pair[pair_code], first_row=first_row, pose=state_pose,
                   load=np.array(list(table.load[first_row]), dtype=str),
                   ref=np.searchsorted(state_pose, state_pose))    # sorted by pose, reference first


def _state_currents(table: StaticTable, states: _States) -> _Currents:
    """The distinct drive readings of each state (distinct_readings), averaged; the currents'
    repeatability from their spread."""
    state, n_states = states.of_row, states.n
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
    return _Currents(mean=cur, n=ncur, sigma=np.sqrt(dev_sq_i / dof_i) if dof_i else None)


def _cells(table: StaticTable, cell: np.ndarray, n_cells: int, good: np.ndarray) -> _Cells:
    """Mean position, readings and mean time of each (state, marker) cell; the tracker's
    repeatability from the ``good`` readings (not outliers) of cells read more than once."""
    count = group_count(cell, n_cells)
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
    var_of = None
    if u95 is not None:             # variance of the mean of the state's readings
        with np.errstate(invalid="ignore", divide="ignore"):
            var_of = group_sum(cell, (u95 / 1.96) ** 2, n_cells) / count.astype(float) ** 2
    return _Cells(count=count, xyz=xyz_mean, t=t_mean, sigma_tracker=float(np.sqrt(dev_sq_p / dof_p)) if dof_p else None,
                  u95_var=var_of, stated_var=_reading_variances(table, cell, count, n_cells), repeated=n_good > 1)


def _noise_level(noise: TrackerNoise | None, stated_law: TrackerNoise | None, cells: _Cells, n_states: int,
                 n_markers: int) -> tuple[TrackerNoise | None, np.ndarray | None, float | None, NoiseSource]:
    """The noise level and where it comes from: the repeats, else the readings' own uncertainty,
    else the law (docs/cli.md); the law in force (a stated one at the repeats' level) and each mean
    reading's covariance (S, M, 3, 3) under it."""
    sigma_tracker = cells.sigma_tracker
    source = (NoiseSource.REPEATS if sigma_tracker is not None else
              NoiseSource.UNCERTAINTY_COLUMNS if cells.stated_var is not None else
              NoiseSource.TRACKER_LAW if noise is not None else NoiseSource.NONE)
    if noise is None:
        return None, None, sigma_tracker, source
    finite = np.all(np.isfinite(cells.xyz), axis=1)
    if source is NoiseSource.REPEATS and noise is stated_law:
        noise = _at_repeats_level(noise, cells.xyz[finite & cells.repeated], sigma_tracker)
    abs_cov = np.full((n_states * n_markers, 3, 3), np.nan)
    abs_cov[finite] = noise.covariance(cells.xyz[finite]) / cells.count[finite][:, None, None]
    if source is NoiseSource.TRACKER_LAW:  # no repeats, no stated uncertainty: the law sets the level
        sigma_tracker = noise.rms_sigma(cells.xyz[finite])
    return noise, abs_cov.reshape(n_states, n_markers, 3, 3), sigma_tracker, source


def _stated_covariance(stated_var: np.ndarray, n_states: int, n_markers: int) -> np.ndarray:
    """(S, M, 3, 3) the readings' stated variances per coordinate on the diagonal."""
    cov = np.zeros((n_states * n_markers, 3, 3))
    cov[:, np.arange(3), np.arange(3)] = stated_var
    return cov.reshape(n_states, n_markers, 3, 3)


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
