"""Constants of the cube-tipping task, read from ``cube_tipping.toml``.

The TOML file beside this module is the single place where the physical constants (masses,
friction coefficients, ball radius, force limits) and the MPC defaults (the reference study's dt, T
and weights) are fixed. :func:`load_config` reads it, or a user's copy, into frozen dataclasses.

Part of the plant-free core: standard library only (no MuJoCo, no CasADi).
"""

from __future__ import annotations

import math
import numbers
import stat
import tomllib
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any

from c3bench.problems.errors import InputError

DEFAULT_CONFIG_PATH = Path(__file__).with_name("cube_tipping.toml")
MAX_CONFIG_BYTES = 1 << 20
"""Largest configuration file read (1 MiB; the packaged one is about 2 kB): a larger file, or
one that is not a regular file (a device such as ``/dev/zero``, a pipe), is refused before it
is read."""
MAX_HORIZON = 200
"""Largest MPC horizon ``T`` (the reference study's is 7): every horizon QP and the MPCC grow
with it (the stacked C3+ QP has some 25 variables per step), and dense matrices with its
square."""
MIN_PLANT_TIMESTEP = 1e-5
"""Smallest plant (MuJoCo) step, in s (the task's is 0.001): a closed-loop second takes
``1 / plant_timestep`` plant steps."""
PERIOD_TOLERANCE = 1e-9
"""Relative tolerance of a period being a whole number of steps (:func:`whole_steps`: the
config's control period, the plant's holds)."""


def _is_number(value: Any) -> bool:
    """A finite real number (``int``, ``float``, a NumPy scalar; not a ``bool``)."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool) \
        and math.isfinite(value)


def _check_pair(name: str, value: Any) -> None:
    """``value`` is a pair of finite numbers."""
    if not (isinstance(value, tuple | list) and len(value) == 2
            and all(_is_number(v) for v in value)):
        raise ValueError(f"{name} must be a pair of finite numbers [a, b], got {value!r}")


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
        if self.plant_timestep < MIN_PLANT_TIMESTEP:
            raise ValueError(f"plant_timestep must be at least {MIN_PLANT_TIMESTEP:g} s, got "
                             f"{self.plant_timestep!r}")
        for name in ("ball_start", "contact_solref"):
            _check_pair(name, getattr(self, name))
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
        if not isinstance(self.horizon, int) or not 1 <= self.horizon <= MAX_HORIZON:
            raise ValueError(f"T (horizon) must be an integer in [1, {MAX_HORIZON}], got "
                             f"{self.horizon!r}")
        for name in ("q_cube_pose", "q_ball_position", "q_velocity", "r_input",
                     "terminal_factor"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {value!r}")
        if not math.isfinite(self.target_angle):
            raise ValueError(f"target_angle must be finite, got {self.target_angle!r}")


def _check_range(name: str, value: Any) -> None:
    """``value`` is a pair ``(low, high)`` of finite numbers with ``low < high``."""
    if not (isinstance(value, tuple) and len(value) == 2
            and all(isinstance(v, int | float) and math.isfinite(v) for v in value)):
        raise ValueError(f"{name} must be a pair [low, high] of finite numbers, got {value!r}")
    if not value[0] < value[1]:
        raise ValueError(f"{name} must have low < high, got {list(value)}")


@dataclass(frozen=True)
class LimitsConfig:
    """The ball workspace of the MPC's state limits (:func:`c3bench.problems.limits.cube_limits`).

    Ranges in m, world frame: ``ball_x`` and ``ball_y`` (spatial scene only) bound the ball
    centre's horizontal coordinates, ``ball_z`` its height; the lower z bound actually used is
    ``max(ball_z[0], table_height + ball_radius)`` (the ball stays above the table).
    """

    ball_x: tuple[float, float] = (-0.60, 0.60)
    ball_y: tuple[float, float] = (-0.40, 0.40)
    ball_z: tuple[float, float] = (0.0, 0.80)

    def __post_init__(self) -> None:
        for name in ("ball_x", "ball_y", "ball_z"):
            _check_range(name, getattr(self, name))


@dataclass(frozen=True)
class Config:
    """Scene, MPC and limit constants together."""

    scene: SceneConfig
    mpc: MPCConfig
    limits: LimitsConfig = LimitsConfig()

    def with_mpc(self, **changes: Any) -> Config:
        """Return a copy with some MPC fields replaced."""
        return replace(self, mpc=replace(self.mpc, **changes))

    def with_scene(self, **changes: Any) -> Config:
        """Return a copy with some scene fields replaced."""
        return replace(self, scene=replace(self.scene, **changes))

    def with_limits(self, **changes: Any) -> Config:
        """Return a copy with some limit fields replaced."""
        return replace(self, limits=replace(self.limits, **changes))


TABLES: dict[str, type] = {"scene": SceneConfig, "mpc": MPCConfig, "limits": LimitsConfig}
"""The tables of a configuration file and the dataclass each fills."""


def _check_type(source: Path, table: str, key: str, value: Any, default: Any) -> None:
    """``value`` of ``[table] key`` has the type of the key's default: a finite number, an
    integer, or a list of as many finite numbers as the default (its range checks come from
    the dataclass); :class:`InputError` naming the file and the key otherwise."""
    if isinstance(default, tuple):
        if not (isinstance(value, list) and len(value) == len(default)
                and all(_is_number(v) for v in value)):
            raise InputError(f"{source}: [{table}] {key} must be a list of {len(default)} "
                             f"finite numbers, got {value!r}")
    elif isinstance(default, int):
        if isinstance(value, bool) or not isinstance(value, int):
            raise InputError(f"{source}: [{table}] {key} must be an integer, got {value!r}")
    elif isinstance(default, float) and not _is_number(value):
        raise InputError(f"{source}: [{table}] {key} must be a finite number, got {value!r}")


def _build(cls: type, name: str, table: Any, source: Path) -> Any:
    """The dataclass ``cls`` from the TOML table ``[name]``; :class:`InputError` naming the
    file, the table and the key at fault."""
    if not isinstance(table, dict):
        raise InputError(f"{source}: {name} must be a table ([{name}]), got a value")
    known = {f.name for f in fields(cls)}
    unknown = set(table) - known
    if unknown:
        raise InputError(f"{source}: unknown key(s) {sorted(unknown)} in [{name}]; known: "
                         f"{', '.join(sorted(known))}")
    defaults = {f.name: f.default for f in fields(cls)}
    for key, value in table.items():
        _check_type(source, name, key, value, defaults[key])
    values = {k: tuple(v) if isinstance(v, list) else v for k, v in table.items()}
    try:
        return cls(**values)
    except (TypeError, ValueError) as error:
        raise InputError(f"{source}: [{name}] {error}") from error


def _check_file(source: Path) -> None:
    """``source`` is a regular file of at most :data:`MAX_CONFIG_BYTES` (checked before it is
    opened: opening a pipe would block, reading a device might never end)."""
    info = source.stat()
    if stat.S_ISDIR(info.st_mode):
        raise IsADirectoryError(source)
    if not stat.S_ISREG(info.st_mode):
        raise InputError(f"{source}: not a regular file (a device, pipe or socket), not a "
                         "configuration file")
    if info.st_size > MAX_CONFIG_BYTES:
        raise InputError(f"{source}: {info.st_size} bytes; a configuration file is at most "
                         f"{MAX_CONFIG_BYTES} bytes (1 MiB)")


def _read_toml(source: Path) -> dict[str, Any]:
    """The tables of a TOML file; :class:`InputError` naming the file when it is missing,
    unreadable, not a regular file, larger than :data:`MAX_CONFIG_BYTES` or not TOML."""
    try:
        _check_file(source)
        with source.open("rb") as handle:
            data = handle.read(MAX_CONFIG_BYTES + 1)
        if len(data) > MAX_CONFIG_BYTES:  # it grew after the check
            raise InputError(f"{source}: a configuration file is at most {MAX_CONFIG_BYTES} "
                             "bytes (1 MiB)")
        return tomllib.loads(data.decode("utf-8"))
    except FileNotFoundError as error:
        raise InputError(f"{source}: no such configuration file") from error
    except IsADirectoryError as error:
        raise InputError(f"{source}: a directory, not a configuration file") from error
    except OSError as error:
        raise InputError(f"{source}: cannot read ({error.strerror or error})") from error
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as error:
        raise InputError(f"{source}: not valid TOML ({error})") from error


def whole_steps(period: float, step: float) -> bool:
    """``period`` is a whole number (>= 1) of ``step`` (to :data:`PERIOD_TOLERANCE`)."""
    count = round(period / step)
    return count >= 1 and abs(count * step - period) <= PERIOD_TOLERANCE * max(1.0, period)


def _check_period(source: Path, scene: SceneConfig, mpc: MPCConfig) -> None:
    """``[mpc] dt`` is a whole number (>= 1) of ``[scene] plant_timestep`` steps."""
    if not whole_steps(mpc.dt, scene.plant_timestep):
        raise InputError(f"{source}: [mpc] dt = {mpc.dt:g} is not a whole multiple of [scene] "
                         f"plant_timestep = {scene.plant_timestep:g} (the plant runs whole "
                         "steps within a control period)")


def load_config(path: str | Path | None = None) -> Config:
    """Read a task configuration.

    Parameters
    ----------
    path
        A TOML file with ``[scene]``, ``[mpc]`` and ``[limits]`` tables; ``None`` reads the
        packaged default.
        Keys left out keep their defaults. An unknown table or key, a missing or unreadable
        file (or one that is not a regular file, or larger than :data:`MAX_CONFIG_BYTES`), a
        value out of range (``horizon`` at most :data:`MAX_HORIZON`, ``plant_timestep`` at
        least :data:`MIN_PLANT_TIMESTEP`), or a ``dt`` that is not a whole number of plant
        steps is an :class:`InputError` naming the file and the table or key.
    """
    if path is not None and not str(path).strip():
        raise InputError("the configuration file's path is empty")
    source = Path(path) if path is not None else DEFAULT_CONFIG_PATH
    table = _read_toml(source)
    unknown = sorted(set(table) - set(TABLES))
    if unknown:
        what = ", ".join(f"[{t}]" if isinstance(table[t], dict) else f"{t} (outside a table)"
                         for t in unknown)
        raise InputError(f"{source}: unknown table(s) {what}; known: "
                         f"{', '.join(f'[{t}]' for t in TABLES)}")
    scene = _build(SceneConfig, "scene", table.get("scene", {}), source)
    mpc = _build(MPCConfig, "mpc", table.get("mpc", {}), source)
    limits = _build(LimitsConfig, "limits", table.get("limits", {}), source)
    _check_period(source, scene, mpc)
    return Config(scene=scene, mpc=mpc, limits=limits)
