"""Constants of the cube-tipping task, read from ``cube_tipping.toml``.

The TOML file beside this module is the single place where the physical constants (masses,
friction coefficients, ball radius, force limits) and the MPC defaults (the reference study's dt, T
and weights) are fixed. :func:`load_config` reads it, or a user's copy, into frozen dataclasses.

Part of the plant-free core: standard library only (no MuJoCo, no CasADi).
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any

DEFAULT_CONFIG_PATH = Path(__file__).with_name("cube_tipping.toml")


def _require_positive(name: str, value: float) -> None:
    if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be a finite number > 0, got {value!r}")


@dataclass(frozen=True)
class SceneConfig:
    """Physical constants of the scene (see ``cube_tipping.toml`` for units and meaning)."""

    cube_side: float = 0.30
    cube_mass: float = 1.0
    ball_radius: float = 0.05
    ball_mass: float = 0.5
    mu_table: float = 0.8
    mu_ball: float = 0.6
    force_limit: float = 30.0
    table_height: float = 0.0
    ball_start: tuple[float, float] = (-0.30, 0.22)
    plant_timestep: float = 0.001
    contact_solref: tuple[float, float] = (0.004, 1.0)

    def __post_init__(self) -> None:
        for name in ("cube_side", "cube_mass", "ball_radius", "ball_mass", "force_limit",
                     "plant_timestep"):
            _require_positive(name, getattr(self, name))
        for name in ("mu_table", "mu_ball"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {value!r}")


@dataclass(frozen=True)
class MPCConfig:
    """The MPC of docs/mpc.md with the reference study's defaults.

    Cost: ``sum_{k<T} (x_k - x*)^T Q (x_k - x*) + u_k^T R u_k + (x_T - x*)^T Q_f (x_T - x*)``
    with ``Q_f = terminal_factor * Q``.
    """

    dt: float = 0.05
    horizon: int = 7
    target_angle: float = 0.5
    q_cube_pose: float = 2.0e5
    q_ball_position: float = 1.0e1
    q_velocity: float = 5.0e2
    r_input: float = 0.01
    terminal_factor: float = 2.0
    success_tolerance: float = 0.1

    def __post_init__(self) -> None:
        _require_positive("dt", self.dt)
        if not isinstance(self.horizon, int) or self.horizon < 1:
            raise ValueError(f"T (horizon) must be an integer >= 1, got {self.horizon!r}")
        for name in ("q_cube_pose", "q_ball_position", "q_velocity", "r_input",
                     "terminal_factor"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {value!r}")
        if not math.isfinite(self.target_angle):
            raise ValueError(f"target_angle must be finite, got {self.target_angle!r}")


@dataclass(frozen=True)
class Config:
    """Scene and MPC constants together."""

    scene: SceneConfig
    mpc: MPCConfig

    def with_mpc(self, **changes: Any) -> Config:
        """Return a copy with some MPC fields replaced."""
        return Config(scene=self.scene, mpc=replace(self.mpc, **changes))

    def with_scene(self, **changes: Any) -> Config:
        """Return a copy with some scene fields replaced."""
        return Config(scene=replace(self.scene, **changes), mpc=self.mpc)


def _build(cls: type, table: dict[str, Any], source: Path) -> Any:
    known = {f.name for f in fields(cls)}
    unknown = set(table) - known
    if unknown:
        raise ValueError(f"{source}: unknown key(s) {sorted(unknown)} in [{cls.__name__}]")
    values = {k: tuple(v) if isinstance(v, list) else v for k, v in table.items()}
    return cls(**values)


def load_config(path: str | Path | None = None) -> Config:
    """Read a task configuration.

    Parameters
    ----------
    path
        A TOML file with ``[scene]`` and ``[mpc]`` tables; ``None`` reads the packaged default.
        Keys left out keep their defaults; an unknown key is an error naming it.
    """
    source = Path(path) if path is not None else DEFAULT_CONFIG_PATH
    with source.open("rb") as handle:
        table = tomllib.load(handle)
    scene = _build(SceneConfig, table.get("scene", {}), source)
    mpc = _build(MPCConfig, table.get("mpc", {}), source)
    return Config(scene=scene, mpc=mpc)
