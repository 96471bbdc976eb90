"""`elastocal view`: the cell in 3-D on a local page (viser), the error made visible.

The robot (from its URDF) at every calibration pose, coloured by how far the
pose's residual sits above the noise floor; the measured and the predicted
marker deflections and the error vectors between them, magnified (×100 by
default, the scale shown on the page); a toggle between the model as given and
the model with the diagnosed effect (and a calibration's prediction with
``--calibration``); the candidate table beside it. docs/view.md.

Needs the optional extra ``pip install 'elastocal[view]'`` (viser). The page is
served on 127.0.0.1 only.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import threading

import numpy as np

from elastocal.commands._inputs import add_input_arguments, add_outlier_argument, add_tracker_arguments, load_inputs
from elastocal.errors import InputError
from elastocal.model.kinds import KinematicForm, TorqueSource

HOST = "127.0.0.1"
ERROR_RGB = (255, 0, 255)        # the error vectors: magenta, a colour nothing else on the page has
MEASURED_RGB = (20, 20, 20)
PREDICTED_RGB = (30, 110, 230)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_input_arguments(parser)
    add_outlier_argument(parser)
    add_tracker_arguments(parser)
    parser.add_argument("--calibration", help="cal.json: also show what this calibration predicts (docs/formats.md §4)")
    parser.add_argument("--add", help="effect shown as 'after' (default: the diagnosis' verdict, else the best "
                                      "plausible candidate)")
    parser.add_argument("--port", type=int, default=8080,
                        help="port of the page on 127.0.0.1 (default 8080; 0 picks a free one)")
    parser.add_argument("--magnify", type=float, default=100.0,
                        help="magnification of the deflections (default 100; the page has a slider)")
    parser.add_argument("--magnify-errors", type=float, default=None,
                        help="magnification of the error vectors, measured - predicted (default: a round "
                             "number that draws the largest error 0.15 m long)")
    parser.add_argument("--pose", default=None,
                        help="the pose shown first: a pose id, or all (default: the pose the model explains "
                             "least; the page's pose menu shows the others)")


def build_view(args: argparse.Namespace):
    """The :class:`~elastocal.report.view.CellView` of the inputs (no viser needed)."""
    from elastocal.commands._inputs import tracker_prior
    from elastocal.commands.diagnose import diagnose_inputs
    from elastocal.model.effects import having, parse_model
    from elastocal.report.view import cell_view

    inputs = load_inputs(args)
    if inputs.static is None:
        raise InputError("the view shows static deflections: give a log or --static table with static poses",
                         source=args.log or "--static")
    model = parse_model(args.model)
    static, _ = diagnose_inputs(inputs, model, TorqueSource(args.torque), KinematicForm(args.form),
                                exclude_outliers=getattr(args, "exclude_outliers", False),
                                prior=tracker_prior(args, inputs))
    calibrated = robot_calibrated = None
    if args.calibration:
        from elastocal.formats.calibration import read_calibration
        from elastocal.diagnose.check import check_static

        cal = read_calibration(args.calibration)
        result = check_static(inputs.robot, cal, inputs.static, form=KinematicForm(args.form))
        if result.measured.shape != static.where.measured.shape or not np.allclose(result.measured,
                                                                                   static.where.measured):
            raise InputError("the calibration's model orders the deflections differently; cannot compare",
                             source=args.calibration)
        calibrated = (f"calibration {args.calibration}", result.predicted)
        if having("geometry", cal.model) and inputs.robot.urdf is None:
            from elastocal.identify.accuracy import calibrated_robot

            robot_calibrated = calibrated_robot(inputs.robot, cal)
    if args.add is not None and args.add not in {c.effect for c in static.candidates}:
        raise InputError(f"{args.add} is not a tested candidate of these data", source="--add")
    return cell_view(inputs.robot, static, add=args.add, calibrated=calibrated, calibrated_robot=robot_calibrated)


class ViewPage:
    """The viser page of one :class:`CellView`; ``server`` is the running ViserServer."""

    def __init__(self, view, *, port: int = 8080, magnify: float = 100.0, magnify_errors: float | None = None,
                 model_index: int | None = None, pose: str | None = None) -> None:
        from elastocal.report.view import auto_magnify_errors, worst_pose

        try:
            import viser
        except ImportError:
            raise InputError("elastocal view needs viser: pip install 'elastocal[view]'", source="view") from None
        self.view = view
        with contextlib.redirect_stdout(sys.stderr):      # viser's banner is not the command's output
            self.server = viser.ViserServer(host=HOST, port=port, label=f"elastocal view: {view.robot_name}",
                                            verbose=False)
        self.server.gui.configure_theme(control_width="large", show_share_button=False)
        self.server.initial_camera.position = (3.6, -3.2, 2.4)
        self.server.initial_camera.look_at = (0.9, 0.0, 0.9)
        self._lock = threading.Lock()
        self.model_index = (0 if model_index is None else model_index) % len(view.models)
        self.magnify = float(magnify)
        self.magnify_errors = float(auto_magnify_errors(view) if magnify_errors is None else magnify_errors)
        # one pose first (the worst): twelve robots overlaid hide each other's arrows
        self.pose = worst_pose(view) if pose is None else pose
        if self.pose not in ("all", *view.pose_ids):
            raise InputError(f"no pose {self.pose!r}; the data have {', '.join(view.pose_ids)} (or all)",
                             source="--pose")
        self.geometry = "nominal"
        self._build_gui()
        self._draw()

    @property
    def url(self) -> str:
        return f"http://{HOST}:{self.server.get_port()}/"

    # ------------------------------------------------------------------ gui
    def _build_gui(self) -> None:
        gui, view = self.server.gui, self.view
        titles = [m.title for m in view.models]
        self.gui_model = gui.add_dropdown("model", options=titles, initial_value=titles[self.model_index])
        self.gui_magnify = gui.add_slider("deflections ×", min=10.0, max=2000.0, step=10.0,
                                          initial_value=self.magnify)
        self.gui_errors = gui.add_slider("errors ×", min=10.0, max=max(5000.0, 4 * self.magnify_errors), step=10.0,
                                         initial_value=self.magnify_errors)
        self.gui_pose = gui.add_dropdown("pose", options=["all", *view.pose_ids], initial_value=self.pose)
        self.gui_geometry = None
        if view.skeletons_calibrated is not None:
            self.gui_geometry = gui.add_dropdown("geometry", options=["nominal", "calibrated"],
                                                 initial_value="nominal")

            @self.gui_geometry.on_update
            def _(_event) -> None:
                self.geometry = self.gui_geometry.value
                self._draw()
        self.gui_scale = gui.add_markdown("")
        self.gui_summary = gui.add_markdown("")
        rows = view.candidates
        table = ["| " + " | ".join(rows[0]) + " |", "|" + "---|" * len(rows[0])]
        table += ["| " + " | ".join(r) + " |" for r in rows[1:]]
        verdict = view.verdict or "none: no candidate is significant and plausible, or the model sits at the floor"
        gui.add_markdown(f"**Verdict:** {verdict}\n\n**Candidate effects**\n\n" + "\n".join(table))
        gui.add_markdown("Poses: green at the noise floor (residual ≤ 1.5× floor), amber above (≤ 3×), "
                         "red far above. Grey lines: the measured deflection of each marker from its "
                         "rigid position; black dots measured, blue predicted; magenta: the error "
                         "(measured − predicted), from the measured dot.")

        @self.gui_model.on_update
        def _(_event) -> None:
            self.model_index = titles.index(self.gui_model.value)
            self._draw()

        @self.gui_magnify.on_update
        def _(_event) -> None:
            self.magnify = float(self.gui_magnify.value)
            self._draw()

        @self.gui_errors.on_update
        def _(_event) -> None:
            self.magnify_errors = float(self.gui_errors.value)
            self._draw()

        @self.gui_pose.on_update
        def _(_event) -> None:
            self.pose = self.gui_pose.value
            self._draw()

    # ---------------------------------------------------------------- scene
    def _draw(self) -> None:
        from elastocal.report.view import arrow_heads, arrows, geometry_skeletons, pose_summary, ratio_colours

        with self._lock:
            view, scene = self.view, self.server.scene
            model = view.models[self.model_index]
            scene.set_up_direction("+z")
            scene.add_grid("/floor", width=4.0, height=4.0, cell_size=0.25, position=(0.6, 0.0, 0.0))
            colours = ratio_colours(model.pose_ratio)
            shown = [p for p, pid in enumerate(view.pose_ids) if self.pose in ("all", pid)]
            skeletons = geometry_skeletons(view, self.geometry == "calibrated", self.magnify)
            for p, pid in enumerate(view.pose_ids):
                pts = skeletons[p]
                segments = np.stack([pts[:-1], pts[1:]], axis=1)
                scene.add_line_segments(f"/poses/{pid}/links", segments, tuple(int(c) for c in colours[p]),
                                        thickness=0.035, visible=p in shown)
                scene.add_point_cloud(f"/poses/{pid}/joints", pts[1:-1], colors=(60, 60, 60), point_size=0.05,
                                      point_shape="circle", visible=p in shown)
            sel = np.isin(view.defl_pose, shown)
            measured, predicted, deflections, errors = arrows(view, model, self.magnify, self.magnify_errors)
            scene.add_line_segments("/markers/deflections", deflections[sel], (150, 150, 150), thickness=0.006)
            scene.add_point_cloud("/markers/measured", measured[sel], colors=MEASURED_RGB, point_size=0.03,
                                  point_shape="circle")
            scene.add_point_cloud("/markers/predicted", predicted[sel], colors=PREDICTED_RGB, point_size=0.03,
                                  point_shape="circle")
            scene.add_line_segments("/markers/errors", errors[sel], ERROR_RGB, thickness=0.012)
            if sel.any():            # arrow heads: which way the measurement is off the model
                scene.add_line_segments("/markers/error_heads", arrow_heads(errors[sel]), ERROR_RGB,
                                        thickness=0.012)
            # the scales: 1 mm of deflection and 100 µm of error, magnified, beside the base
            bar = 1e-3 * self.magnify
            scene.add_line_segments("/scale/deflection", np.array([[[0.0, -0.8, 0.0], [bar, -0.8, 0.0]]]),
                                    (0, 0, 0), thickness=0.01)
            scene.add_label("/scale/deflection_label", f"1 mm of deflection (×{self.magnify:g})",
                            position=(0.0, -0.9, 0.0))
            bar = 1e-4 * self.magnify_errors
            scene.add_line_segments("/scale/error", np.array([[[0.0, -1.1, 0.0], [bar, -1.1, 0.0]]]), ERROR_RGB,
                                    thickness=0.01)
            scene.add_label("/scale/error_label", f"100 µm of error (×{self.magnify_errors:g})",
                            position=(0.0, -1.2, 0.0))
            floor = "no noise floor (no repeated readings)" if view.noise_floor is None else \
                f"noise floor {view.noise_floor * 1e6:.1f} µm"
            self.gui_scale.content = (f"**{model.title}**: residual rms {model.rms * 1e6:.1f} µm, {floor}. "
                                      f"Deflections ×{self.magnify:g} (the black bar: 1 mm), errors "
                                      f"×{self.magnify_errors:g} (the magenta bar: 100 µm).")
            if view.skeletons_calibrated is not None:
                shift = np.linalg.norm(view.skeletons_calibrated - view.skeletons, axis=2).max()
                self.gui_scale.content += (f" Geometry: **{self.geometry}**" +
                                           (f" (its difference from nominal ×{self.magnify:g}; largest joint-origin "
                                            f"shift {shift * 1e3:.2f} mm)." if self.geometry == "calibrated" else "."))
            self.gui_summary.content = "**Poses** (residual rms)\n\n" + "\n".join(
                f"- {line}" for line in pose_summary(view, model))

    def stop(self) -> None:
        self.server.stop()


def run(args: argparse.Namespace) -> int:
    view = build_view(args)
    if not 0 <= args.port <= 65535:
        raise InputError(f"{args.port} is not a port (0..65535)", source="--port")
    for flag, value in (("--magnify", args.magnify), ("--magnify-errors", args.magnify_errors)):
        if value is not None and not value > 0:
            raise InputError(f"must be positive, got {value:g}", source=flag)
    page = ViewPage(view, port=args.port, magnify=args.magnify, magnify_errors=args.magnify_errors,
                    pose=args.pose)
    info = {"url": page.url, "poses": len(view.pose_ids), "verdict": view.verdict,
            "models": [m.title for m in view.models], "magnify": args.magnify,
            "magnify_errors": page.magnify_errors, "pose": page.pose}
    if args.json:
        print(json.dumps(info), flush=True)
    else:
        print(f"elastocal view: {page.url} (Ctrl-C stops it); {len(view.pose_ids)} poses, "
              f"models: {'; '.join(info['models'])}", flush=True)
    try:
        threading.Event().wait()
    finally:
        page.stop()
    return 0
