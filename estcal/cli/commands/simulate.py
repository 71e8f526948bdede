"""``estcal simulate``: a simulated calibration dataset with its ground truth
(:func:`estcal.workflows.simulate.simulate`; ``--fleet N``: :func:`estcal.workflows.simulate.simulate_fleet`)."""
from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from estcal.cli.app import command
from estcal.cli.options import deprecated_option, json_option, noise_pos_option, noise_rot_option, root_option, tip_option

__all__ = ["simulate"]


@command("simulate")
def simulate(
    robot: str = typer.Option("puma560", "--robot", "-r",
                              help="Built-in name (`estcal robots`), robot file (.yaml) or URDF (.urdf)."),
    n: int = typer.Option(50, "--n", "-n", help="Number of poses."),
    strategy: str = typer.Option("S4", help="Pose strategy: S1 (together), S2 (one joint at a time), "
                                            "S3 (one held), S4 (uniform random)."),
    measure: str = typer.Option("position", "--measure", help="position | points | pose."),
    noise_pos_mm: float = noise_pos_option(0.0, "; half-width if uniform"),
    noise_rot_mrad: float = noise_rot_option(0.0, "; half-width if uniform"),
    noise_joint_mrad: float = typer.Option(0.0, "--noise-joint-mrad", help="Joint-reading noise σ (mrad; mm "
                                                                           "for prismatic joints)."),
    resolution_mrad: float = typer.Option(0.0, "--resolution-mrad", help="Encoder resolution (mrad; mm for "
                                                                         "prismatic joints); 0 = none."),
    noise_dist: str = typer.Option("gaussian", "--noise-dist", help="gaussian | uniform."),
    errors: str = typer.Option("random", help="random | none | JSON/YAML file {parameter: error}."),
    error_angle_mrad: float = typer.Option(1.0, "--error-angle-mrad", help="σ of random angle errors (mrad)."),
    error_length_mm: float = typer.Option(1.0, "--error-length-mm", help="σ of random length errors (mm)."),
    error_offset_mrad: float = typer.Option(1.0, "--error-offset-mrad", help="σ of random joint-offset errors "
                                                                             "(mrad; mm for prismatic joints)."),
    error_gain: float = typer.Option(0.0, "--error-gain", help="σ of random joint-gain errors."),
    effects: Optional[List[str]] = typer.Option(
        None, "--effects", "-e",
        help="Effect NAME[:JOINT,JOINT] (repeat, or separate with ';'), e.g. joint_compliance:j2,j3."),
    effect_param: Optional[List[str]] = typer.Option(
        None, "--effect-param", help="NAME=VALUE for an effect parameter in SI units like the robot file, "
                                     "e.g. compliance_j2=2e-6 (rad/(N·m)) (repeat)."),
    seed: int = typer.Option(0, help="Random seed."),
    margin: float = typer.Option(0.0, help="Fraction of each joint range left out at both ends."),
    dt: Optional[float] = typer.Option(None, "--dt", help="Seconds between poses (writes a t column)."),
    temperature: Optional[str] = typer.Option(
        None, help="Temperature °C: T, or START,END (linear), or START,END,TAU (warm-up, needs --dt)."),
    payload: Optional[str] = typer.Option(None, help="Payload kg: M, or LO,HI (uniform per pose)."),
    approach: bool = typer.Option(False, "--approach", help="Record approach_<joint> columns for backlash."),
    n_points: int = typer.Option(3, "--points", help="Markers added for --measure points if the robot has none."),
    root: Optional[str] = root_option(),
    tip: Optional[str] = tip_option(),
    output: Optional[Path] = typer.Option(None, "--output", "-o", help="Dataset CSV to write."),
    truth: Optional[Path] = typer.Option(None, "--truth", help="Ground-truth JSON to write."),
    true_model: Optional[Path] = typer.Option(
        None, "--true-model", help="Robot file (.yaml) to write with the true robot (nominal + errors + "
                                   "effects), for --robot: e.g. run compensated commands on it with estcal fk."),
    json_path: Optional[Path] = json_option("Write the summary as JSON."),
    old_noise_pos: Optional[float] = deprecated_option("--noise-pos"),
    old_noise_rot: Optional[float] = deprecated_option("--noise-rot"),
    old_noise_joint: Optional[float] = deprecated_option("--noise-joint"),
    old_resolution: Optional[float] = deprecated_option("--resolution"),
    old_error_angle: Optional[float] = deprecated_option("--error-angle"),
    old_error_length: Optional[float] = deprecated_option("--error-length"),
    old_error_offset: Optional[float] = deprecated_option("--error-offset"),
    from_fit: Optional[Path] = typer.Option(
        None, "--from-fit", help="Diagnosis fit (estcal diagnose --json): simulate the robot as identified "
                                 "(geometric + named effects); --errors/--effects are ignored, the noise "
                                 "defaults to the fit's, --measure position means the fit's kind."),
    fleet: Optional[int] = typer.Option(
        None, "--fleet", help="Simulate a fleet of N robots into --out DIR (one folder per robot: data.csv, "
                              "validate.csv with --n new poses, truth.json; shared DIR/robot.yaml) with "
                              "random errors and, for half of them, one random effect. Noise defaults to "
                              "0.05 mm / 0.5 mrad. Input of estcal fleet."),
    out: Optional[Path] = typer.Option(None, "--out", help="Fleet folder to write (with --fleet)."),
    on_demand: bool = typer.Option(False, "--on-demand", help="With --fleet: write only the fleet's "
                                   "description (--out DIR/fleet.yaml + robot.yaml); estcal fleet simulates "
                                   "robot i from the seed and i in the task that calibrates it, no file per robot."),
    scheduler: str = typer.Option("serial", "--scheduler", help="With --fleet: serial | processes | local | "
                                                                "tcp://host:8786."),
    ) -> None:
    """Simulate a calibration dataset: true robot = nominal + parameter errors + effects.

    Writes the dataset CSV (-o) and the ground truth (--truth) and prints a summary:
    poses, columns, and how far the nominal model is from the truth (RMS/max, mm).
    """
    from estcal.base.errors import InputError
    from estcal.base.units import MILLI
    from estcal.cli.units import resolve
    from estcal.simulate import ErrorModel, NoiseModel
    from estcal.workflows import simulate as wf

    noise_pos = resolve(noise_pos_mm, MILLI, old_noise_pos, "--noise-pos", "--noise-pos-mm", "m", 1.0, 0.0)
    noise_rot = resolve(noise_rot_mrad, MILLI, old_noise_rot, "--noise-rot", "--noise-rot-mrad", "rad", 1.0, 0.0)
    noise_joint = resolve(noise_joint_mrad, MILLI, old_noise_joint, "--noise-joint", "--noise-joint-mrad",
                          "rad or m", 1.0, 0.0)
    resolution = resolve(resolution_mrad, MILLI, old_resolution, "--resolution", "--resolution-mrad", "rad or m",
                         1.0, 0.0)
    error_angle = resolve(error_angle_mrad, MILLI, old_error_angle, "--error-angle", "--error-angle-mrad", "rad",
                          1.0, 1.0)
    error_length = resolve(error_length_mm, MILLI, old_error_length, "--error-length", "--error-length-mm", "m",
                           1.0, 1.0)
    error_offset = resolve(error_offset_mrad, MILLI, old_error_offset, "--error-offset", "--error-offset-mrad",
                           "rad or m", 1.0, 1.0)
    if true_model is not None and true_model.suffix.lower() not in (".yaml", ".yml"):
        raise InputError(f"--true-model {true_model}: a robot file must end in .yaml or .yml")
    if on_demand and fleet is None:
        raise InputError("--on-demand describes a fleet: give --fleet N --out DIR")
    if fleet is not None:
        rr = wf.simulate_fleet(fleet, out, robot=robot, n=n, measure=measure, noise_pos=noise_pos,
                               noise_rot=noise_rot, seed=seed, scheduler=scheduler, on_demand=on_demand)
        if on_demand:
            typer.echo(f"fleet of {rr.robots:,} robots described in {out}/fleet.yaml ({rr.poses} calibration + "
                       f"{rr.validation_poses} validation poses each, {rr.measure}, noise {1e3 * rr.noise_pos:.3g} mm / "
                       f"{1e3 * rr.noise_rot:.3g} mrad, seed {rr.seed}); each robot is simulated by the task that "
                       f"calibrates it: estcal fleet {out}")
            return
        _print_fleet(rr, out, n, measure, noise_pos, noise_rot, json_path)
        return
    noise = NoiseModel(position=noise_pos, orientation=noise_rot, joint=noise_joint, resolution=resolution,
                       distribution=noise_dist)
    given = noise_pos or noise_rot or noise_joint or resolution
    res = wf.simulate(robot, n, strategy=strategy, measure=measure,
                      noise=noise if (from_fit is None or given) else None, errors=errors,
                      error_std=ErrorModel(angle=error_angle, length=error_length, offset=error_offset, gain=error_gain),
                      effects=effects or [], effect_params=effect_param or [], seed=seed, margin=margin, dt=dt,
                      temperature=temperature, payload=payload, approach=approach, n_points=n_points, root=root,
                      tip=tip, from_fit=from_fit)
    _write_and_print(res, output, truth, true_model, json_path)


def _write_and_print(res, output, truth, true_model, json_path) -> None:
    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    from estcal.base.jsonio import write_json

    csv_path = truth_path = None
    if output is not None:
        csv_path, truth_path = res.write(output, truth)
    elif truth is not None:
        write_json(truth, res.truth)
        truth_path = truth
    if true_model is not None:
        from estcal.io.robotfile import save_robot

        save_robot(res.true_robot, true_model)
    table = Table(title=f"estcal simulate — {res.summary.robot}", show_header=False)
    table.add_column("item", style="bold")
    table.add_column("value")
    for k, v in res.summary.rows():
        table.add_row(k, escape(v))
    if csv_path:
        table.add_row("dataset", str(csv_path))
    if truth_path:
        table.add_row("ground truth", str(truth_path))
    if true_model is not None:
        table.add_row("true robot file", str(true_model))
    console = Console()
    console.print(table)
    for note in res.summary.notes:
        console.print("[yellow]note:[/yellow] " + escape(note))
    if json_path is not None:
        out = res.summary.to_dict()
        out["dataset"] = str(csv_path) if csv_path else None
        out["truth"] = str(truth_path) if truth_path else None
        write_json(json_path, out)


def _print_fleet(rr, out, n, measure, noise_pos, noise_rot, json_path) -> None:
    from rich.console import Console

    console = Console()
    measure = "pose" if measure in ("position", "location") else measure
    for f in rr.failures:
        console.print(f"[red]failed:[/red] {f}")
    rows = [r for r in rr.results if r is not None]
    with_eff = [r for r in rows if r["effects"]]
    console.print(f"fleet of {len(rows)} robots in {out}/ ({n} calibration + {n} validation poses each, "
                  f"{measure}, noise {1e3 * (noise_pos or 5e-5):.3g} mm / {1e3 * (noise_rot or 5e-4):.3g} mrad); "
                  f"{len(with_eff)} with an effect: " + (", ".join(f"{r['robot']} {r['effects'][0]}"
                                                                   for r in with_eff[:6]) or "none")
                  + (" …" if len(with_eff) > 6 else ""), soft_wrap=True)
    if json_path is not None:
        from estcal.base.jsonio import write_json

        write_json(json_path, {"fleet": str(out), "robots": rows, "failures": [f.to_dict() for f in rr.failures]})
    if rr.failures:
        raise typer.Exit(2)
