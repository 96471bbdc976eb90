"""The ``[sim]`` section of cell.toml: parameters of the simulated cell.

The drivers keep this section as the raw table (:attr:`CellConfig.sim`); the
simulation reads it through :func:`sim_config`, which validates every key, so
errors name the file and the key. The effects the simulated cell can hide are
listed once, in :data:`elastocal.sims.cell.HIDDEN_EFFECTS`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

from elastocal.drivers.config import _int, _num, _vec
from elastocal.errors import InputError, check_known_keys
from elastocal.sims.cell import HIDDEN_EFFECTS


@dataclass(frozen=True)
class SimConfig:
    """Parameters of the simulated cell (``elastocal sim serve``)."""

    seed: int = 0
    hidden: str = "none"
    start_q: tuple[float, ...] = (0.0, 0.2, -0.4, 0.0, 0.5, 0.0)
    move_speed_rad_s: float = 0.5
    run_speed_rad_s: float = 0.05
    coulomb_nm: tuple[float, ...] = (40.0, 90.0, 70.0, 12.0, 10.0, 6.0)
    viscous_nm_s_rad: tuple[float, ...] = (300.0, 600.0, 450.0, 60.0, 50.0, 30.0)
    load_friction: tuple[float, ...] = (0.02, 0.02, 0.02, 0.03, 0.03, 0.03)
    tracker_noise_m: float = 10e-6
    current_noise_a: float = 0.02
    gear_ratios: tuple[float, ...] = (150.0, 160.0, 140.0, 80.0, 80.0, 60.0)
    can_reply_delay_s: float = 50e-6
    modbus_reply_delay_s: float = 0.0
    tracker_reply_delay_s: float = 0.0
    #: the load rig of a served cell (sims/load_rig.py): written by ``sim serve --write-cell``
    load_url: str = ""


def _sim(t: Mapping, *, source: str) -> SimConfig:
    where = "sim"
    if not isinstance(t, Mapping):
        raise InputError("expected a table", source=source, column=where)
    d = SimConfig()
    check_known_keys(t, tuple(SimConfig.__dataclass_fields__), source=source, where=where)
    hidden = t.get("hidden", d.hidden)
    if not isinstance(hidden, str) or not all(h.strip() in HIDDEN_EFFECTS for h in hidden.split(",")):
        raise InputError(f"hidden must be one of {', '.join(HIDDEN_EFFECTS)} (or several, comma-separated), "
                         f"got {hidden!r}", source=source, column="sim.hidden")
    kw = dict(
        seed=_int(t, "seed", d.seed, source=source, where=where),
        hidden=hidden,
        start_q=_vec(t, "start_q", d.start_q, source=source, where=where),
        move_speed_rad_s=_num(t, "move_speed_rad_s", d.move_speed_rad_s, source=source, where=where),
        run_speed_rad_s=_num(t, "run_speed_rad_s", d.run_speed_rad_s, source=source, where=where),
        coulomb_nm=_vec(t, "coulomb_nm", d.coulomb_nm, source=source, where=where, nonneg=True),
        viscous_nm_s_rad=_vec(t, "viscous_nm_s_rad", d.viscous_nm_s_rad, source=source, where=where, nonneg=True),
        load_friction=_vec(t, "load_friction", d.load_friction, source=source, where=where, nonneg=True),
        tracker_noise_m=_num(t, "tracker_noise_m", d.tracker_noise_m, source=source, where=where, positive=False),
        current_noise_a=_num(t, "current_noise_a", d.current_noise_a, source=source, where=where, positive=False),
        gear_ratios=_vec(t, "gear_ratios", d.gear_ratios, source=source, where=where),
        can_reply_delay_s=_num(t, "can_reply_delay_s", d.can_reply_delay_s, source=source, where=where,
                               positive=False),
        modbus_reply_delay_s=_num(t, "modbus_reply_delay_s", d.modbus_reply_delay_s, source=source, where=where,
                                  positive=False),
        tracker_reply_delay_s=_num(t, "tracker_reply_delay_s", d.tracker_reply_delay_s, source=source,
                                   where=where, positive=False),
        load_url=t.get("load_url", d.load_url),
    )
    if not isinstance(kw["load_url"], str):
        raise InputError("expected a modbus+tcp:// URL on 127.0.0.1", source=source, column="sim.load_url")
    for key in ("tracker_noise_m", "current_noise_a", "can_reply_delay_s", "modbus_reply_delay_s",
                "tracker_reply_delay_s"):
        if kw[key] < 0:
            raise InputError("must be >= 0", source=source, column=f"sim.{key}")
    if any(g <= 0 for g in kw["gear_ratios"]):
        raise InputError("gear ratios must be > 0", source=source, column="sim.gear_ratios")
    return SimConfig(**kw)


def sim_config(config) -> SimConfig:
    """The validated ``[sim]`` section of a :class:`~elastocal.drivers.config.CellConfig`; a
    ``load_url`` is a modbus+tcp URL on 127.0.0.1 that shares no register with the cell's devices."""
    sim = _sim(config.sim, source=config.source)
    if sim.load_url:
        from elastocal.drivers.config import _cell_devices
        from elastocal.drivers.endpoints import check_endpoints
        from elastocal.drivers.load_rig import LOOPBACK, WRENCH
        from elastocal.drivers.urls import parse_device_url

        url = parse_device_url(sim.load_url, allowed=("modbus+tcp",), source=f"{config.source}, sim.load_url")
        if url.host not in LOOPBACK:
            raise InputError(f"{url.text}: a simulated cell's load rig is on 127.0.0.1", source=config.source,
                             column="sim.load_url")
        check_endpoints([*_cell_devices(config), ("load rig", url, (WRENCH,))], source=config.source)
    return sim
