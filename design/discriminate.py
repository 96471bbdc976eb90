"""Experiments that tell effects apart (docs/plan.md, "The next experiment").

When ``diagnose`` cannot test an effect on the data it has, or cannot tell it
from another, the next experiment should be the one that settles it. The
criterion is the **expected evidence** that diagnose will compute: its test of
an effect E against a model is a Wald statistic whose expectation, when E is
present at size ``s``, is ``q + lambda`` with the non-centrality (linearised
model, deflection noise with shared references as the fit weights it)::

    lambda(E | O) = trace( diag(s) S_E|O diag(s) ),   S_E|O = M_EE - M_EO M_OO^-1 M_OE

``M`` the Fisher information of the data (given log plus planned round), ``O``
the parameters E must be told from: the model's (joint springs and what the
model holds) and, in turn, each rival effect's. The expected delta BIC of E is
``-(lambda + q) + q ln n``: the design makes it decisive (below diagnose's
-10) against the model *and* against every rival, which is model discrimination
(the expected log Bayes factor of the two nested Gaussian models). The size ``s``
is the smallest size of each parameter worth finding (``Effect.design_size``),
or what the given log fitted when that is larger.

The search picks poses from sampled candidates (design/candidates.py: joint
limits, heights, the tracker's line of sight) and per pose the load forces
from the rig's directions at its largest force; greedy on the sum over
(effect, rival) of ``log(1 + lambda)`` so that the weakest pair gains most.
Loads of one pose are counted as if each had its own reference reading (their
shared reference makes the real information a little larger).

A round is worth its time only when it turns an open question into a decided
one: the given data would not already show an effect of the size worth
finding, and the planned round is expected to (delta BIC below -10 against the
model and every rival). Otherwise the plan says why not.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from elastocal.errors import InputError
from elastocal.design.candidates import Workspace, load_directions, sample_candidates
from elastocal.diagnose.verdict import VERDICT_DELTA_BIC
from elastocal.identify.design_matrix import planned_dataset, refusals, regressor
from elastocal.identify.static import StaticDataset
from elastocal.model.effects import ALL_EFFECTS, BASE_EFFECT, get_effect
from elastocal.model.robot import DEFAULT_PRIOR_STIFFNESS, Robot

#: time model of the static procedure [s]: a move to a pose, a load change, one marker reading
#: (settling and averaging included)
MOVE_S = 30.0
LOAD_CHANGE_S = 45.0
READING_S = 2.0
#: ridge of the normalised nuisance information (parameters no data see carry none)
RIDGE = 1e-9
#: a parameter that keeps less than this share of its information once told from the model
#: and a rival, over every candidate pose and load, is that model under another name
REACHABLE = 1e-6


@dataclass(frozen=True)
class Evidence:
    """What diagnose is expected to find of one effect at its design size."""

    effect: str
    size: tuple[tuple[str, float], ...]    # (parameter, the size the design must show)
    delta_bic_given: float                 # against the model, the given data alone
    delta_bic: float                       # against the model, given data plus the planned round
    rival: str | None                      # the rival it is hardest to tell from (after the round)
    delta_bic_rival: float                 # against the model with that rival
    delta_bic_rival_given: float           # the same on the given data alone
    delta_bic_random: float | None = None  # median of random rounds of the same size (rival-separated)
    weakest: str | None = None             # the parameter hardest to show after the round

    @property
    def decided_by_given(self) -> bool:
        return self.delta_bic_rival_given < VERDICT_DELTA_BIC

    @property
    def decided_after(self) -> bool:
        return self.delta_bic_rival < VERDICT_DELTA_BIC

    def to_json(self) -> dict:
        return {"effect": self.effect, "size": dict(self.size), "delta_bic_given": self.delta_bic_given,
                "delta_bic": self.delta_bic, "rival": self.rival, "delta_bic_rival": self.delta_bic_rival,
                "delta_bic_rival_given": self.delta_bic_rival_given, "delta_bic_random": self.delta_bic_random,
                "weakest": self.weakest,
                "decided_by_given": self.decided_by_given, "decided_after": self.decided_after}


@dataclass(frozen=True, eq=False)
class DiscriminatingDesign:
    """Poses and their load forces that separate the target effects, and what they are expected to show."""

    q: np.ndarray                          # (n, N) poses
    forces: np.ndarray                     # (K, 3) load forces used, base axes [N]
    pose_loads: tuple[tuple[int, ...], ...]  # per pose: rows of ``forces``
    evidence: tuple[Evidence, ...]
    rivals: tuple[str, ...]
    time_s: float                          # the round's procedure time (MOVE_S, LOAD_CHANGE_S, READING_S)
    worth: bool
    reason: str                            # why the round is (not) worth its time

    @property
    def n_states(self) -> int:
        return sum(len(p) for p in self.pose_loads)


@dataclass(frozen=True)
class GivenData:
    """The data already measured and what their fit says (the first log's model and noise)."""

    dataset: StaticDataset | None
    model: tuple[str, ...]
    compliance: np.ndarray                 # (N,) fitted joint compliances [rad/(N·m)]
    sigma_tracker: float                   # per reading [m]
    sigma_current: np.ndarray | None       # (N,) per reading [A]
    fitted: tuple[tuple[str, float], ...] = ()   # effect parameters the given data fitted: (name, value)
    noise_source: str = ""


def procedure_time_s(n_poses: int, n_states: int, n_markers: int, repeats: int) -> float:
    """Time of a static round: moves, load changes, readings of the references and the loads."""
    return n_poses * MOVE_S + n_states * LOAD_CHANGE_S + (n_poses + n_states) * n_markers * repeats * READING_S


def rival_pool(model: Sequence[str], targets: Sequence[str]) -> tuple[str, ...]:
    """The static effects with parameters the model lacks, other than the targets: what a target
    could be mistaken for (absolute-position effects are told apart by the absolute comparison)."""
    from elastocal.identify.absolute import ABSOLUTE_EFFECTS

    out = []
    for name in ALL_EFFECTS:
        eff = get_effect(name)
        if (name in model or name in targets or name in ABSOLUTE_EFFECTS or "static" not in eff.seen_in
                or not eff.parameters or eff.static_basis is None):
            continue
        out.append(name)
    return tuple(out)


def _information(a: np.ndarray, ds: StaticDataset, sigma: float, group: np.ndarray) -> np.ndarray:
    """(G, p, p) Fisher information of the deflections per group (``group``: (D,) index),
    tracker noise ``sigma`` per reading, deflections of one marker and pose sharing their
    reference reading: cov = sigma^2 (diag(1/n) + 1 1'/n_ref) per coordinate."""
    a = np.nan_to_num(a)
    n_groups = int(group.max()) + 1 if group.size else 0
    out = np.zeros((n_groups, a.shape[2], a.shape[2]))
    pose_of = ds.state_pose[ds.defl_state]
    key = pose_of * len(ds.markers) + ds.defl_marker
    for k in np.unique(key):
        rows = np.flatnonzero(key == k)
        cov = sigma**2 * (np.diag(1.0 / ds.defl_n[rows]) + 1.0 / ds.defl_n_ref[rows[0]])
        w = np.linalg.inv(cov)
        for axis in range(3):
            x = a[rows, axis, :]
            out[group[rows[0]]] += x.T @ w @ x
    return out


def _noncentrality(m: np.ndarray, target: np.ndarray, others: np.ndarray) -> np.ndarray:
    """(K, |target|) non-centrality of each target parameter at its design size, alone,
    told from ``others`` (the diagonal of the Schur complement of the target block), for a
    stack of information matrices (K, p, p) scaled so that a unit is the design size."""
    mee = m[:, target][:, :, target]
    if others.size:
        moo = m[:, others][:, :, others]
        d = np.sqrt(np.clip(np.einsum("kii->ki", moo), 1e-300, None))
        moo_n = moo / d[:, :, None] / d[:, None, :] + RIDGE * np.eye(len(others))
        moe = m[:, others][:, :, target] / d[:, :, None]
        s = mee - np.swapaxes(moe, 1, 2) @ np.linalg.solve(moo_n, moe)
    else:
        s = mee
    return np.clip(np.einsum("kii->ki", s), 0.0, None)


def _delta_bic(lam: float, n: int) -> float:
    """Expected delta BIC of diagnose's test of one parameter of non-centrality ``lam``:
    -(lambda + 1) + ln n."""
    return float(-(lam + 1.0) + math.log(max(n, 2)))


class _Problem:
    """Parameter layout, sizes and the information of the given data."""

    def __init__(self, robot: Robot, given: GivenData, targets: Sequence[str], rivals: Sequence[str]):
        self.robot, self.given, self.targets, self.rivals = robot, given, tuple(targets), tuple(rivals)
        model_extra = tuple(m for m in given.model if m != BASE_EFFECT and m not in targets)
        self.effects = tuple(dict.fromkeys([*model_extra, *targets, *rivals]))
        names = (BASE_EFFECT, *self.effects)
        self.param_names = tuple(p for n in names for p in get_effect(n).parameters)
        self.block = {}
        start = 0
        for n in names:
            k = len(get_effect(n).parameters)
            self.block[n] = np.arange(start, start + k)
            start += k
        self.base = np.concatenate([self.block[n] for n in (BASE_EFFECT, *model_extra)])
        fitted = dict(given.fitted)
        scale = np.ones(len(self.param_names))
        scale[self.block[BASE_EFFECT]] = given.compliance
        self.size: dict[str, np.ndarray] = {}
        for n in targets:
            eff = get_effect(n)
            if eff.design_size is None:
                raise InputError(f"{n}: no size worth finding is known for this effect, so no experiment can be "
                                 "planned to show it", argument="discriminate")
            s = np.asarray(eff.design_size(given.compliance), dtype=float)
            s = np.maximum(s, [abs(fitted.get(p, 0.0)) for p in eff.parameters])   # the fitted model, if larger
            self.size[n] = s
            scale[self.block[n]] = s
        self.scale = scale
        self.beta = np.zeros(len(self.param_names))
        self.beta[self.block[BASE_EFFECT]] = given.compliance
        self.m_given = np.zeros((len(self.param_names),) * 2)
        self.n_given = 0
        if given.dataset is not None:
            self.m_given = self.information(given.dataset)[0]
            self.n_given = 3 * given.dataset.n_deflections

    def information(self, ds: StaticDataset, group: np.ndarray | None = None) -> np.ndarray:
        a, names = regressor(self.robot, ds, self.effects, beta=self.beta)
        assert names == self.param_names
        a = a * self.scale                      # a unit of each parameter is its design (or typical) size
        group = np.zeros(ds.n_deflections, dtype=np.intp) if group is None else group
        return _information(a, ds, self.given.sigma_tracker, group)

    def pairs(self):
        """(target, rival or None, target indices, nuisance indices)."""
        for t in self.targets:
            for r in (None, *(x for x in (*self.targets, *self.rivals) if x != t)):
                others = self.base if r is None else np.concatenate([self.base, self.block[r]])
                yield t, r, self.block[t], others

    def set_reachable(self, m_pool: np.ndarray) -> None:
        """Per (target, rival): the target's parameters some experiment within the workspace can
        tell from the model and the rival (``m_pool``: the information of every candidate). The
        others are the same motion under another name (a wrist link's bending is joint springs
        plus link 3's at a spherical wrist) and are left out of that comparison."""
        self.reachable = {}
        for t, r, tgt, oth in self.pairs():
            s = _noncentrality(m_pool[None], tgt, oth)[0]
            own = np.clip(np.diag(m_pool)[tgt], 1e-300, None)
            self.reachable[(t, r)] = s / own > REACHABLE
            
    def _lams(self, m: np.ndarray):
        for t, r, tgt, oth in self.pairs():
            keep = self.reachable[(t, r)]
            yield t, r, _noncentrality(m, tgt[keep], oth), np.asarray(get_effect(t).parameters)[keep]

    def score(self, m: np.ndarray) -> np.ndarray:
        """(K,) design criterion of stacked information matrices: the sum over (target, rival)
        and the target's parameters of log(1 + lambda), so that the weakest gain most."""
        total = np.zeros(len(m))
        for _, _, lam, _ in self._lams(m):
            total += np.log1p(lam).sum(axis=1)
        return total

    def evidence(self, m_new: np.ndarray, n_new: int, m_random: Sequence[np.ndarray] = (),
                 n_random: int = 0) -> tuple[Evidence, ...]:
        """Per target: the expected delta BIC of its weakest parameter at its design size, against
        the model and against its hardest rival, with the given data, after the round, and after
        random rounds."""
        stack = np.array([self.m_given, self.m_given + m_new, *(self.m_given + r for r in m_random)])
        n_all = [self.n_given, self.n_given + n_new] + [self.n_given + n_random] * len(m_random)
        out = []
        for t in self.targets:
            rows = [(r, lam, names) for tt, r, lam, names in self._lams(stack) if tt == t]
            dbic = [[_delta_bic(float(np.median(lam[k])) if lam.shape[1] else 0.0, n_all[k]) for k in range(len(stack))]
                    for _, lam, _ in rows]
            worst = int(np.argmax([d[1] for d in dbic[1:]])) + 1 if len(rows) > 1 else 0
            lam0 = rows[0][1][1]
            weakest = str(rows[0][2][int(np.argmin(lam0))]) if lam0.size else None
            worst_random = [max(d[k] for d in dbic) for k in range(2, len(stack))]
            out.append(Evidence(
                effect=t, size=tuple(zip(get_effect(t).parameters, map(float, self.size[t]))),
                delta_bic_given=dbic[0][0], delta_bic=dbic[0][1], rival=rows[worst][0],
                delta_bic_rival=max(d[1] for d in dbic), delta_bic_rival_given=max(d[0] for d in dbic),
                delta_bic_random=float(np.median(worst_random)) if worst_random else None,
                weakest=weakest))
        return tuple(out)


def _item_information(pr: _Problem, q: np.ndarray, forces: np.ndarray, markers: Sequence[str],
                      repeats: int) -> np.ndarray:
    """(C, F, p, p) information of each candidate pose under each load force, each with its reference."""
    n_c, n_f = len(q), len(forces)
    wrenches = [np.concatenate([f, np.zeros(3)])[None, :] for _ in range(n_c) for f in forces]
    ds = planned_dataset(pr.robot, np.repeat(q, n_f, axis=0), wrenches, markers, repeats=repeats,
                         sigma_tracker=pr.given.sigma_tracker, sigma_current=pr.given.sigma_current)
    group = ds.state_pose[ds.defl_state]
    m = pr.information(ds, group)
    return m.reshape(n_c, n_f, *m.shape[1:])


def _greedy(pr: _Problem, items: np.ndarray, n_poses: int, loads_per_pose: int) -> list[tuple[int, int]]:
    """Pick (pose, force) items one at a time, best criterion first, at most ``n_poses`` poses
    and ``loads_per_pose`` forces per pose."""
    n_c, n_f = items.shape[:2]
    flat = items.reshape(n_c * n_f, *items.shape[2:])
    chosen: list[tuple[int, int]] = []
    m = pr.m_given.copy()
    for _ in range(n_poses * loads_per_pose):
        used = {}
        for c, f in chosen:
            used[c] = used.get(c, 0) + 1
        ok = np.ones((n_c, n_f), dtype=bool)
        for c, f in chosen:
            ok[c, f] = False
        for c in range(n_c):
            if c in used and used[c] >= loads_per_pose:
                ok[c] = False
            elif c not in used and len(used) >= n_poses:
                ok[c] = False
        idx = np.flatnonzero(ok.reshape(-1))
        if idx.size == 0:
            break
        scores = pr.score(m[None] + flat[idx])
        best = int(idx[int(np.argmax(scores))])
        chosen.append(divmod(best, n_f))
        m = m + flat[best]
    return chosen


def plan_discrimination(robot: Robot, given: GivenData, targets: Sequence[str], workspace: Workspace, *,
                        markers: Sequence[str], n_poses: int = 6, loads_per_pose: int = 2, n_candidates: int = 150,
                        repeats: int = 3, seed: int = 0, n_random: int = 20) -> DiscriminatingDesign:
    """The round of at most ``n_poses`` poses (``loads_per_pose`` load forces each, of the rig's
    largest size) that makes every target decisive against the model and its rivals."""
    if n_poses < 1 or loads_per_pose < 1:
        raise InputError("poses and loads per pose must be at least 1", argument="poses")
    rng = np.random.default_rng(seed)
    cands = sample_candidates(robot, n_candidates, rng, workspace, markers)
    forces = workspace.f_max_n * load_directions(workspace.directions, robot.gravity)
    # what no candidate experiment can show (the torque source's refusals) is neither target nor rival
    pool = planned_dataset(robot, np.repeat(cands.q, len(forces), axis=0),
                           [np.concatenate([f, np.zeros(3)])[None, :] for _ in cands.q for f in forces], markers,
                           repeats=repeats, sigma_tracker=given.sigma_tracker, sigma_current=given.sigma_current)
    refused = refusals(robot, pool, (*targets, *rival_pool(given.model, targets)))
    for t in targets:
        if t in refused:
            raise InputError(f"{t}: no pose and load of the workspace can show it: {refused[t]}",
                             argument="discriminate")
    rivals = tuple(r for r in rival_pool(given.model, targets) if r not in refused)
    pr = _Problem(robot, given, targets, rivals)
    items = _item_information(pr, cands.q, forces, markers, repeats)
    pr.set_reachable(pr.m_given + items.sum(axis=(0, 1)))
    chosen = _greedy(pr, items, n_poses, loads_per_pose)
    poses = list(dict.fromkeys(c for c, _ in chosen))
    pose_loads = tuple(tuple(f for c2, f in chosen if c2 == c) for c in poses)
    m_new = sum(items[c, f] for c, f in chosen)
    randoms = []
    for _ in range(n_random):           # random rounds of the same size, same forces on offer
        cs = rng.choice(len(cands.q), len(poses), replace=False)
        randoms.append(sum(items[c, f] for c in cs
                           for f in rng.choice(len(forces), min(loads_per_pose, len(forces)), replace=False)))
    n_states = len(chosen)
    n_new = 3 * n_states * len(markers)
    evidence = pr.evidence(m_new, n_new, randoms, 3 * len(poses) * min(loads_per_pose, len(forces)) * len(markers))
    time_s = procedure_time_s(len(poses), n_states, len(markers), repeats)
    worth, reason = _worth(evidence, time_s)
    used = sorted({f for _, f in chosen})
    remap = {f: k for k, f in enumerate(used)}
    return DiscriminatingDesign(q=cands.q[poses], forces=forces[used],
                                pose_loads=tuple(tuple(remap[f] for f in fl) for fl in pose_loads),
                                evidence=evidence, rivals=rivals, time_s=time_s, worth=worth, reason=reason)


def _worth(evidence: Sequence[Evidence], time_s: float) -> tuple[bool, str]:
    """A round is worth its time when it decides an effect the given data leave open."""
    hours = time_s / 3600.0
    open_ = [e for e in evidence if not e.decided_by_given]
    if not open_:
        return False, ("the given data already decide every effect named at the size worth finding "
                       "(diagnose them: what they do not name is not there at that size)")
    decided = [e for e in open_ if e.decided_after]
    if not decided:
        worst = max(open_, key=lambda e: e.delta_bic_rival)
        return False, (f"a round of this size is not expected to decide {worst.effect} (expected ΔBIC "
                       f"{worst.delta_bic_rival:+.0f} against {worst.rival or 'the model'}, -10 needed): "
                       "allow more poses or larger loads")
    gain = sum(e.delta_bic_rival_given - e.delta_bic_rival for e in decided)
    return True, (f"it decides {', '.join(e.effect for e in decided)} that the given data leave open: expected "
                  f"evidence gain {gain:.0f} (ΔBIC) in {hours * 60:.0f} min, {gain / hours:.0f} per hour")


def given_from_diagnosis(diag, *, noise_source: str = "the given data's repeated readings",
                         sigma_tracker: float | None = None, sigma_current: np.ndarray | None = None) -> GivenData:
    """The given data as a static diagnosis (diagnose/static.py) saw them: its final model (with
    the effects it added) and that model's joint springs, its measured noise (else the values
    given), and what it fitted of each candidate."""
    fit = diag.final          # the model with the effects the diagnosis added: what the data say so far
    ds = diag.fit.dataset
    n = ds.q.shape[1]
    fitted_k = {p.name: p.value for p in fit.parameters}
    # a joint spring the given data do not determine keeps the prior (its compliance only scales
    # the nuisance columns; the targets' sizes do not depend on it except nonlinear ones)
    known = [v for j in range(1, n + 1) if (v := fitted_k.get(f"k{j}", 0.0)) > 0]
    priors = [DEFAULT_PRIOR_STIFFNESS[j - 1] if j <= len(DEFAULT_PRIOR_STIFFNESS)
              else float(np.median(known)) if known else DEFAULT_PRIOR_STIFFNESS[-1] for j in range(1, n + 1)]
    k = np.array([fitted_k[f"k{j}"] if fitted_k.get(f"k{j}", 0.0) > 0 else priors[j - 1] for j in range(1, n + 1)])
    fitted = []
    for c in diag.candidates:
        for name, value in zip(c.fit.beta_names, c.fit.beta):
            if name in get_effect(c.effect).parameters:
                fitted.append((name, float(value)))
    st = ds.sigma_tracker if ds.sigma_tracker is not None else sigma_tracker
    if st is None:
        raise InputError("the given data have no repeated readings: give the tracker noise", argument="tracker_noise")
    sc = ds.sigma_current if ds.sigma_current is not None else sigma_current
    return GivenData(dataset=ds, model=tuple(fit.model), compliance=1.0 / k, sigma_tracker=float(st),
                     sigma_current=sc, fitted=tuple(fitted),
                     noise_source=noise_source if ds.sigma_tracker is not None else "the noise given")
