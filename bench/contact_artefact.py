"""The friction-cone artefact of Anitescu's relaxation, measured on the scene's LCS.

Anitescu's convex relaxation [1] replaces the Coulomb cone by one force per friction
direction along ``n + mu t_j`` and writes complementarity on the velocity along each such
direction: ``0 <= lam_j  perp  phi / dt + (n + mu t_j)^T v' >= 0``. A contact that slides with
tangential velocity ``v_t'`` (after the step) has its active direction opposite to the
motion, ``t_j^T v' = -|v_t'|``, so at ``phi = 0`` it must separate with normal velocity

    v_n' = mu |v_t'|,    gap after one step  phi' = dt mu |v_t'|.

Stewart and Trinkle's formulation [2] keeps the position-level gap ``phi + dt v_n'`` itself in
complementarity with the normal force, so a loaded sliding contact stays closed (``v_n' = 0``).

:func:`measure_artefact` measures both on the scene's ball-table contact: the ball resting on
the table, pressed down by ``press`` newtons and sliding in +x at a range of speeds, one LCS
step (Lemke) with each contact model, and the MuJoCo plant stepped ``dt`` from the same state
for comparison. For the gravity-compensated ball of mass ``m`` the step has a closed form:
while sliding, Stewart-Trinkle gives Coulomb's ``v_t' = v_t - dt mu press / m`` and Anitescu
``v_t' = (v_t - dt mu press / m) / (1 + mu^2)`` with ``v_n' = mu v_t'`` (the separating
velocity takes part of the friction impulse). :func:`plot_artefact` draws the gap after the
step against ``|v_t'|`` with the line ``dt mu |v_t|``.

``python -m c3bench.bench.contact_artefact [--out PNG]`` writes the figure
(default ``docs/figures/anitescu_artefact.png``) and prints the measured slopes.

References
----------
[1] M. Anitescu, "Optimization-based simulation of nonsmooth rigid multibody dynamics",
    Mathematical Programming 105 (2006) 113-143.
[2] D. E. Stewart and J. C. Trinkle, "An implicit time-stepping scheme for rigid body
    dynamics with inelastic collisions and Coulomb friction", IJNME 39 (1996) 2673-2691.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from c3bench.problems.config import Config, load_config
from c3bench.problems.lcs import ContactModel
from c3bench.problems.linearize import linearize
from c3bench.problems.scene import Plant, Scene, build_scene, home_state
from c3bench.solvers.lcp import lemke

MODELS: tuple[ContactModel, ...] = ("anitescu", "stewart_trinkle")
DEFAULT_FIGURE = Path("docs/figures/anitescu_artefact.png")


@dataclass
class ArtefactMeasurement:
    """One LCS step of a ball sliding on the table, per initial speed and contact model.

    Attributes
    ----------
    speeds
        Initial tangential (x) speeds of the ball (m/s).
    tangential
        Per model: the tangential speed after the step, ``|v_t'|`` (m/s).
    normal
        Per model: the normal (z) velocity after the step, ``v_n'`` (m/s).
    gap
        Per model: the ball-table gap after the step, ``phi'`` (m).
    plant_gap, plant_tangential
        MuJoCo's gap and tangential speed after ``dt`` from the same state (soft contact,
        1 ms steps).
    mu, dt, press, mass
        Friction coefficient of the ball-table pair, LCS step, downward force (N) and ball
        mass (kg).
    """

    speeds: np.ndarray
    tangential: dict[str, np.ndarray]
    normal: dict[str, np.ndarray]
    gap: dict[str, np.ndarray]
    plant_gap: np.ndarray
    plant_tangential: np.ndarray
    mu: float
    dt: float
    press: float
    mass: float


def sliding_ball_state(scene: Scene, speed: float) -> np.ndarray:
    """The scene at rest except the ball: on the table (``phi = 0``), 0.3 m left of the cube's
    near face (out of its reach within one step), moving at ``speed`` in +x."""
    x = home_state(scene)
    ball = scene.ball_position_indices
    r = scene.config.scene.ball_radius
    x[ball[0]] = -scene.l / 2 - r - 0.3
    x[ball[-1]] = scene.config.scene.table_height + r
    x[scene.nq + ball[0] - (scene.nq - scene.nv)] = speed
    return x


def measure_artefact(speeds: np.ndarray | None = None, press: float = 10.0,
                     config: Config | None = None) -> ArtefactMeasurement:
    """Measure the gap after one LCS step of the sliding ball (module docstring).

    Parameters
    ----------
    speeds
        Initial tangential speeds (m/s); default 0 to 3 m/s in 31 steps.
    press
        Downward force on the ball (N), the contact's normal load.
    config
        Task constants (default: the packaged ones); the planar scene with its ball-table
        contact.
    """
    cfg = config or load_config()
    speed_values = np.linspace(0.0, 3.0, 31) if speeds is None else np.asarray(speeds, float)
    scene = build_scene(config=cfg)
    dt = cfg.mpc.dt
    u = np.zeros(scene.nu)
    u[-1] = -press
    ball = scene.ball_position_indices
    vx, vz = scene.nq + ball[0] - (scene.nq - scene.nv), scene.nq + ball[-1] - (scene.nq - scene.nv)
    floor = cfg.scene.table_height + cfg.scene.ball_radius
    tangential: dict[str, np.ndarray] = {m: np.zeros(speed_values.size) for m in MODELS}
    normal: dict[str, np.ndarray] = {m: np.zeros(speed_values.size) for m in MODELS}
    gap: dict[str, np.ndarray] = {m: np.zeros(speed_values.size) for m in MODELS}
    plant_gap, plant_tangential = np.zeros(speed_values.size), np.zeros(speed_values.size)
    plant = Plant(scene)
    for i, speed in enumerate(speed_values):
        x = sliding_ball_state(scene, float(speed))
        for model in MODELS:
            lcs = linearize(scene, x, u, dt, model)
            solution = lemke(lcs.F, lcs.lcp_offset(x, u))
            if not solution.found or solution.z is None:
                raise RuntimeError(f"Lemke failed on the {model} step at {speed} m/s: "
                                   f"{solution.status}")
            after = lcs.next_state(x, u, solution.z)
            tangential[model][i] = abs(after[vx])
            normal[model][i] = after[vz]
            gap[model][i] = after[ball[-1]] - floor
        plant.reset(x)
        after = plant.step(u, dt)
        plant_gap[i] = after[ball[-1]] - floor
        plant_tangential[i] = abs(after[vx])
    return ArtefactMeasurement(
        speeds=speed_values, tangential=tangential, normal=normal, gap=gap,
        plant_gap=plant_gap, plant_tangential=plant_tangential, mu=cfg.scene.mu_table,
        dt=dt, press=press, mass=cfg.scene.ball_mass)


def plot_artefact(measurement: ArtefactMeasurement, path: str | Path = DEFAULT_FIGURE
                  ) -> Path:
    """Gap after one step against the tangential speed after it, both contact models, the
    plant and the line ``dt mu |v_t|``; written as PNG to ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    m = measurement
    figure, axis = plt.subplots(figsize=(6.4, 4.2), constrained_layout=True)
    top = max(float(np.max(m.tangential["anitescu"])), 1e-3)
    line = np.linspace(0.0, top, 50)
    axis.plot(line, 1e3 * m.dt * m.mu * line, color="#7f7f7f", linestyle="--",
              label=r"theory $\Delta t\,\mu\,|v_t|$")
    axis.plot(m.tangential["anitescu"], 1e3 * m.gap["anitescu"], "o", color="#d62728",
              label="LCS, Anitescu")
    axis.plot(m.tangential["stewart_trinkle"], 1e3 * m.gap["stewart_trinkle"], "s",
              color="#1f77b4", mfc="none", label="LCS, Stewart-Trinkle")
    axis.plot(m.plant_tangential, 1e3 * m.plant_gap, "^", color="#2ca02c", mfc="none",
              label="MuJoCo plant (soft contact)")
    axis.set_xlabel(r"tangential speed after the step $|v_t'|$ (m/s)")
    axis.set_ylabel(r"ball-table gap after one step (mm)")
    axis.set_title(f"Sliding ball pressed on the table ({m.press:g} N, "
                   rf"$\mu$ = {m.mu:g}, $\Delta t$ = {m.dt:g} s, n = {m.speeds.size} speeds)",
                   fontsize=9)
    axis.grid(alpha=0.3)
    axis.legend(loc="upper left", fontsize=8)
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(out, dpi=120)
    plt.close(figure)
    return out


def separation_slope(measurement: ArtefactMeasurement, model: ContactModel) -> float:
    """Least-squares slope of ``v_n'`` against ``|v_t'|`` over the sliding points
    (``|v_t'| > 1e-9``); ``mu`` for Anitescu, 0 for Stewart-Trinkle."""
    t, n = measurement.tangential[model], measurement.normal[model]
    sliding = t > 1e-9
    if not np.any(sliding):
        return float("nan")
    return float(n[sliding] @ t[sliding] / (t[sliding] @ t[sliding]))


def main(argv: list[str] | None = None) -> int:
    """Write the figure and print the measured slopes."""
    parser = argparse.ArgumentParser(prog="python -m c3bench.bench.contact_artefact",
                                     description="Measure Anitescu's friction-cone artefact.")
    parser.add_argument("--out", default=str(DEFAULT_FIGURE), metavar="PNG",
                        help=f"figure path (default: {DEFAULT_FIGURE})")
    parser.add_argument("--press", type=float, default=10.0, metavar="N",
                        help="downward force on the ball (default: 10)")
    args = parser.parse_args(argv)
    measurement = measure_artefact(press=args.press)
    path = plot_artefact(measurement, args.out)
    for model in MODELS:
        print(f"{model:16s} v_n' / |v_t'| = {separation_slope(measurement, model):.6f} "
              f"(mu = {measurement.mu:g}); max gap after one step "
              f"{1e3 * float(np.max(measurement.gap[model])):.3f} mm")
    print(f"plant            max |gap| after {measurement.dt:g} s "
          f"{1e3 * float(np.max(np.abs(measurement.plant_gap))):.3f} mm")
    print(f"figure           {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
