"""What ``elastocal identify`` and ``elastocal diagnose`` compute from loaded data.

A robot and its tables in, the command's ``--json`` object (or the diagnoses)
out. The commands and :mod:`elastocal.fleet` call these same functions, so a
log analysed alone and in a fleet gives the same numbers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from elastocal.errors import InputError
from elastocal.formats.calibration import (
    CalibratedParameter,
    Calibration,
    Residual,
    is_stiffness_name,
    make_calibration,
)
from elastocal.identify.absolute import ABSOLUTE_EFFECTS, AbsoluteFit
from elastocal.model.effects import ALL_EFFECTS, get_effect
from elastocal.model.kinds import KinematicForm, TorqueSource


def absolute_or_static(robot, table, model: tuple[str, ...], torque: TorqueSource, form: KinematicForm, *,
                       tracker_prior=None):
    """The absolute fit (identify/absolute.py) when the table holds absolute
    positions or the model has absolute effects, else the deflection fit."""
    from elastocal.identify.absolute import ABSOLUTE_EFFECTS, has_absolute_positions, identify_absolute
    from elastocal.identify.static import build_dataset, identify_static

    ds = build_dataset(table)
    if has_absolute_positions(robot, ds) or any(m in ABSOLUTE_EFFECTS for m in model):
        return identify_absolute(robot, ds, model=model, torque=torque, form=form, tracker_prior=tracker_prior)
    return identify_static(robot, ds, model=model, torque=torque, form=form)


@dataclass(frozen=True, eq=False)
class Identification:
    """What ``elastocal identify`` finds in the tables, typed: the static (or absolute) fit, the
    runs' fit, the readings left out. The ``--json`` object (:meth:`to_json`) and the calibration
    file (:meth:`calibration`) are both made from it; neither is made from the other."""

    model: tuple[str, ...]
    #: the static or absolute fit (None: run data only)
    fit: object | None
    #: the run-data fit (identify/runs.py RunFit; None without runs)
    runs: object | None
    #: static readings far off their repeats (identify/outliers.py), excluded or not
    outliers: tuple = ()
    #: where the tracker position the absolute fit's registration was held to came from (cell.toml)
    prior_source: str | None = None

    def parameters(self) -> tuple[CalibratedParameter, ...]:
        """Every parameter found, in the ``--json`` object's order: the static fit's with each joint
        stiffness that is not a result marked (identify/evidence.py), then the runs' (a run
        parameter the static fit also gives takes that one's place)."""
        from elastocal.identify.evidence import stiffness_problem

        out: dict[str, CalibratedParameter] = {}
        if self.fit is not None:
            for p in self.fit.parameters:
                why = stiffness_problem(float(p.value), float(p.std or 0.0)) if is_stiffness_name(p.name) else None
                out[p.name] = CalibratedParameter(p.name, p.value, p.std, p.unit, determined=False if why else None,
                                                  note=why)
        if self.runs is not None:
            for p in self.runs.parameters:
                out[p.name] = CalibratedParameter(p.name, p.value, p.std, p.unit)
        return tuple(out.values())

    def _residuals(self) -> tuple[Residual, Residual | None]:
        """The fitted data's residual [m] (run data only: the torques' [N·m]) and the absolute one."""
        if self.fit is None:
            r = self.runs
            peak = float(np.max(np.abs(r.residuals))) if r.residuals.size else float("nan")
            return Residual(rms=r.rms, max=peak, n=int(r.residuals.size), noise_floor=r.noise_floor), None
        fit = self.fit
        if not isinstance(fit, AbsoluteFit):
            return Residual(rms=fit.rms, max=fit.max, n=fit.n, noise_floor=fit.noise_floor), None
        static = fit.static                           # the deflection fit the absolute one started from
        absolute = Residual(rms=fit.rms, max=fit.max, n=fit.n, noise_floor=fit.noise_floor)
        if any(m in ABSOLUTE_EFFECTS for m in fit.model):
            deflection = Residual(rms=fit.deflection_rms, max=fit.deflection_max,
                                  n=int(fit.deflection_residuals.size), noise_floor=static.noise_floor)
        else:
            deflection = Residual(rms=static.rms, max=static.max, n=static.n, noise_floor=static.noise_floor)
        return deflection, absolute

    def calibration(self, robot_name: str, data_paths=(), *, created: str | None = None,
                    robot_description: str | None = None) -> Calibration:
        """The calibration (docs/formats.md §4) of these results and the files they came from."""
        residual, absolute = self._residuals()
        if self.fit is None:
            torque = TorqueSource.CURRENT
        else:
            torque = (self.fit.static if isinstance(self.fit, AbsoluteFit) else self.fit).torque
        return make_calibration(robot_name, model=self.model, torque=torque, parameters=self.parameters(),
                                residual=residual, absolute_residual=absolute, data_paths=data_paths,
                                created=created, robot_description=robot_description,
                                unidentifiable=self.unidentifiable())

    def unidentifiable(self) -> tuple[str, ...]:
        """The parameters the data cannot separate (not held: the calibration reads them as absent)."""
        if self.fit is None:
            return tuple(self.runs.unidentifiable)
        if isinstance(self.fit, AbsoluteFit):
            return tuple(self.fit.unidentifiable or self.fit.static.unidentifiable)
        return tuple(self.fit.unidentifiable)

    def to_json(self) -> dict:
        """The ``identify --json`` object (docs/cli.md)."""
        if self.fit is None:
            return self.runs.to_json()
        obj = self.fit.to_json()
        obj["model"] = list(self.model)
        obj["outliers"] = [o.to_json() for o in self.outliers]
        if self.prior_source is not None and "prior" in obj.get("registration", {}):
            obj["registration"]["prior"]["source"] = self.prior_source
        if self.runs is not None:
            rj = self.runs.to_json()
            obj["parameters"].update(rj["parameters"])
            obj["torque_residual"] = rj["residual"]
            obj["torque_noise_floor"] = rj["noise_floor"]
        return obj


def identify_data(robot, static, runs, model: tuple[str, ...], torque: TorqueSource, form: KinematicForm, *,
                  exclude_outliers: bool = False, tracker_prior=None,
                  prior_source: str | None = None, progress=None) -> Identification:
    """What ``identify`` finds in the tables (:class:`Identification`). ``outliers`` lists the
    static readings far off their repeats (identify/outliers.py); with ``exclude_outliers`` the
    fit leaves them out. ``tracker_prior``: where the tracker stands in base coordinates [m]
    (cell.toml's, ``prior_source`` naming where it was read). ``progress``: told of each fit,
    ``progress(done, label, total=...)`` (elastocal/progress.py)."""
    from elastocal.identify.outliers import without_outliers

    fits = (static is not None) + (runs is not None)

    def stage(done: int, label: str) -> None:
        if progress is not None:
            progress(done, label, total=fits)

    if static is None:
        stage(0, "fitting the runs")
        from elastocal.identify import runs as run_ident  # run data: compensator, friction

        result = run_ident.identify_runs(robot, runs, model=model)
        return Identification(model=tuple(result.model), fit=None, runs=result)
    from elastocal.identify.runs import RUN_EFFECTS

    run_model = tuple(m for m in model if m in RUN_EFFECTS)
    static_model = tuple(m for m in model if m not in RUN_EFFECTS or runs is None)
    table, excluded = without_outliers(static) if exclude_outliers else (static, ())
    stage(0, f"fitting {' + '.join(static_model)} to the static table")
    fit = absolute_or_static(robot, table, static_model, torque, form, tracker_prior=tracker_prior)
    run_fit = None
    if runs is not None and run_model:
        from elastocal.identify import runs as run_ident

        stage(1, "fitting the runs")
        # the sweeps placed with the static fit's stiffness
        k = [p.value for p in fit.parameters if is_stiffness_name(p.name)]
        run_fit = run_ident.identify_runs(robot, runs, model=("joint_stiffness", *run_model),
                                          stiffness=k if len(k) == robot.n_joints else None)
    return Identification(model=tuple(model), fit=fit, runs=run_fit,
                          outliers=(*excluded, *fit.dataset.outliers), prior_source=prior_source)


def diagnose_data(robot, static, runs, model: tuple[str, ...], torque: TorqueSource, form: KinematicForm, *,
                  log: str | None = None, exclude_outliers: bool = False, tracker_prior=None, progress=None):
    """(static Diagnosis or None, run Diagnosis or None) for the tables; ``log``
    names the log they came from, for the error when there is nothing to diagnose;
    ``tracker_prior``: where the tracker stands in base coordinates [m], a prior on
    the registration of the absolute comparison; ``progress``: told of each fit
    (``progress(done, label, total=...)``, elastocal/progress.py)."""
    from elastocal.diagnose.static import diagnose_static

    static_diag = None
    runs_diag = None
    if static is not None and runs is None and static.absolute_only:     # a table without loads
        from elastocal.diagnose.absolute_only import diagnose_absolute_only
        from elastocal.identify.outliers import without_outliers
        from elastocal.identify.static import build_dataset

        table, excluded = without_outliers(static) if exclude_outliers else (static, ())
        return diagnose_absolute_only(robot, build_dataset(table), model, tracker_prior=tracker_prior), None
    if static is not None:
        static_model = model
        if runs is not None:  # run-data effects of the model are the runs' business
            static_model = tuple(m for m in model if "static" in get_effect(m).seen_in)
        pool = tuple(e for e in ALL_EFFECTS if e not in model)
        static_diag = diagnose_static(robot, static, model=static_model, torque=torque, form=form, effects=pool,
                                      exclude_outliers=exclude_outliers, tracker_prior=tracker_prior,
                                      progress=progress)
    if runs is not None:
        if progress is not None:
            progress(0, "the runs' friction and compensator", total=1)
        from elastocal.diagnose.runs import diagnose_runs

        stiffness = None
        if static_diag is not None:
            stiffness = [p.value for p in static_diag.fit.parameters if p.name.startswith("k")]
            stiffness = stiffness if len(stiffness) == robot.n_joints else None
        runs_diag = diagnose_runs(robot, runs, model=model, stiffness=stiffness)
    if static_diag is None and runs_diag is None:
        if log is not None:
            raise InputError("nothing to diagnose: the log holds neither a static experiment nor runs", source=log)
        raise InputError("nothing to diagnose: give a static table and/or runs", argument="static")
    return static_diag, runs_diag


def diagnosis_json(static, runs) -> dict:
    """The ``diagnose --json`` object (docs/cli.md): the static diagnosis when there is
    one, the run diagnosis alone otherwise. With both, the run diagnosis is under
    ``runs`` too, and ``candidates`` and ``verdict`` cover both data: every
    candidate says which data tested it (``data``: static or runs), significant
    ones first by delta_bic, and the verdict is the first when it is its own
    data's verdict — so null still means "no missing effect found" in either."""
    from elastocal.diagnose.absolute_only import AbsoluteOnlyDiagnosis

    if isinstance(static, AbsoluteOnlyDiagnosis):
        return static.to_json()
    if static is None:
        obj = runs.to_json()
        for c in obj["candidates"]:
            c["data"] = "runs"
        return obj
    obj = static.to_json()
    for c in obj["candidates"]:
        c["data"] = "static"
    if runs is None:
        return obj
    obj["runs"] = runs.to_json()
    tagged = [*obj["candidates"], *({**c, "data": "runs"} for c in obj["runs"]["candidates"])]
    tagged.sort(key=lambda c: (not c["significant"], c["delta_bic"]))
    obj["candidates"] = tagged
    verdicts = {"static": static.verdict, "runs": runs.verdict}
    obj["verdict"] = tagged[0]["effect"] if tagged and verdicts[tagged[0]["data"]] == tagged[0]["effect"] else None
    return obj
