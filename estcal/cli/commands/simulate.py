"""``estcal simulate``: a simulated calibration dataset with its ground truth."""
from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from estcal.cli.common import fail, message
from estcal.cli.units import deprecated_option, noise_pos_option, noise_rot_option
from estcal.base.jsonio import write_json


def _floats(text: str | None, what: str):
    if text is None:
        return None
    parts = [p for p in text.replace(";", ",").split(",") if p.strip()]
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        raise typer.BadParameter(f"{what}: expected numbers separated by commas, got {text!r}") from None
    return vals[0] if len(vals) == 1 else vals


def _load_errors(errors: str):
    low = errors.lower()
    if low in ("none", "random"):
        return low
    p = Path(errors)
    if not p.exists():
        raise typer.BadParameter(f"--errors must be 'random', 'none' or a JSON/YAML file of {{name: delta}}; "
                                 f"{errors!r} is none of these")
    from estcal.base.textinput import read_json, read_yaml

    if p.suffix.lower() in (".yaml", ".yml"):
        d = read_yaml(p, "errors", ValueError)
    else:
        d = read_json(p, "errors", ValueError)
    if isinstance(d, dict) and "errors" in d and isinstance(d["errors"], dict):
        d = d["errors"]  # a truth JSON from an earlier run
    if not isinstance(d, dict):
        raise typer.BadParameter(f"{p}: expected a mapping {{parameter name: error}}")
    out = {}
    for k, v in d.items():
        if isinstance(v, bool) or not isinstance(v, (int, float)) or v != v or abs(v) == float("inf"):
            raise ValueError(f"{p}: error of {k!r} must be a finite number (SI), got {v!r}")
        out[str(k)] = float(v)
    return out


def _check_errors(errs: dict, robot, where) -> None:
    """The names of an errors file must be the robot's, and its values SI: an angle error beyond
    π, a length error beyond 1 m or a relative gain error beyond 1 is a unit mistake (degrees,
    millimetres, per cent), not a robot to calibrate."""
    import math

    from estcal.base.units import display_unit
    from estcal.kinematics.parameters import unknown_name_message

    for k, v in errs.items():
        if k not in robot.params:
            raise ValueError(f"{where}: {unknown_name_message(k, robot.params.names)}")
        unit = display_unit(k, robot)[0]
        limit, what = {"mrad": (math.pi, "rad (degrees?)"), "mm": (1.0, "m (millimetres?)"),
                       "": (1.0, "(relative; per cent?)")}.get(unit, (math.inf, ""))
        if abs(v) > limit:
            raise ValueError(f"{where}: the error of {k!r} is {v:g} {what} — the file is in SI units "
                             f"(m, rad, relative gain); beyond ±{limit:g} no calibration model applies")


#: measured peak memory of `estcal simulate` per pose (0.8 kB position, 1.0 kB three points at 2·10⁵
#: poses; docs/benchmarks.md "Memory on large datasets"), with a margin for effects and context columns
BYTES_PER_POSE = 1500


def _available_memory() -> int | None:
    """MemAvailable of /proc/meminfo in bytes (None where there is no such file)."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def check_memory(n: int) -> None:
    """Refuse, before the work, a simulation that would not fit in the memory available now
    (the dataset is built whole, then written atomically): a clear message instead of the
    operating system killing the process after minutes."""
    avail = _available_memory()
    need = n * BYTES_PER_POSE
    if avail is not None and need > 0.8 * avail:
        fail(f"--n {n}: simulating {n:,} poses needs about {need / 1e9:.1f} GB of memory and {avail / 1e9:.1f} GB "
             f"are available — simulate several smaller files (different --seed) or lower --n")


def _simulate_fleet(console, n_robots, out, robot, n, measure, noise_pos, noise_rot, seed, scheduler, json_path):
    from estcal.cli.common import fail
    from estcal.scale.runner import check_scheduler
    from estcal.scale.simfleet import simulate_fleet

    if out is None:
        fail("--fleet needs --out DIR (the fleet folder to write)")
    if n_robots < 1:
        fail(f"--fleet: the number of robots must be ≥ 1, got {n_robots}")
    try:
        check_scheduler(scheduler)
    except ValueError as exc:
        fail(f"--scheduler: {exc}")
    if measure == "position":  # a fleet is measured as full poses unless asked otherwise
        measure = "pose"
    try:
        rr = simulate_fleet(n_robots, out, robot=robot, n_poses=n, n_validate=n, measure=measure,
                            noise_pos=noise_pos or 5e-5, noise_rot=noise_rot or 5e-4, seed=seed,
                            scheduler=scheduler)
    except (ValueError, KeyError, FileNotFoundError) as exc:
        fail(str(exc))
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
        write_json(json_path, {"fleet": str(out), "robots": rows, "failures": [f.to_dict() for f in rr.failures]})
    if rr.failures:
        raise typer.Exit(2)


def register(app: typer.Typer) -> None:
    @app.command("simulate")
    def simulate_cmd(
        robot: str = typer.Option("puma560", "--robot", "-r",
                                  help="Built-in name, robot file (.yaml) or URDF (.urdf)."),
        n: int = typer.Option(50, "--n", "-n", help="Number of poses."),
        strategy: str = typer.Option("S4", help="Pose strategy: S1 (together), S2 (one joint at a time), "
                                                "S3 (one held), S4 (uniform random)."),
        measure: str = typer.Option("position", help="position | points | pose."),
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
        root: Optional[str] = typer.Option(None, help="URDF root link."),
        tip: Optional[str] = typer.Option(None, help="URDF tip link."),
        output: Optional[Path] = typer.Option(None, "--output", "-o", help="Dataset CSV to write."),
        truth: Optional[Path] = typer.Option(None, "--truth", help="Ground-truth JSON to write."),
        true_model: Optional[Path] = typer.Option(
            None, "--true-model", help="Robot file (.yaml) to write with the true robot (nominal + errors + "
                                       "effects), for --robot: e.g. run compensated commands on it with estcal fk."),
        json_path: Optional[Path] = typer.Option(None, "--json", help="Write the summary as JSON."),
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
        scheduler: str = typer.Option("serial", "--scheduler", help="With --fleet: serial | processes | local | "
                                                                    "tcp://host:8786."),
    ) -> None:
        """Simulate a calibration dataset: true robot = nominal + parameter errors + effects.

        Writes the dataset CSV (-o) and the ground truth (--truth) and prints a summary:
        poses, columns, and how far the nominal model is from the truth (RMS/max, mm).
        """
        from rich.console import Console
        from rich.markup import escape
        from rich.table import Table

        from estcal.io.robotfile import load_robot
        from estcal.simulate import ErrorModel, NoiseModel, simulate

        from estcal.base.units import MILLI
        from estcal.cli.units import resolve

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
        console = Console()
        if true_model is not None and true_model.suffix.lower() not in (".yaml", ".yml"):
            fail(f"--true-model {true_model}: a robot file must end in .yaml or .yml")
        check_memory(n * (fleet or 1))
        if fleet is not None:
            _simulate_fleet(console, fleet, out, robot, n, measure, noise_pos, noise_rot, seed, scheduler,
                            json_path)
            return
        try:
            nominal = load_robot(robot, root=root, tip=tip)
            eff_specs = []
            for e in effects or []:
                eff_specs += [s.strip() for s in e.split(";") if s.strip()]
            from estcal.simulate import parse_effect_spec

            specs = [parse_effect_spec(s) for s in eff_specs]
            eparams = {}
            for item in effect_param or []:
                name, _, val = item.partition("=")
                try:
                    eparams[name.strip()] = float(val)
                except ValueError:
                    raise typer.BadParameter(f"--effect-param expects NAME=VALUE, got {item!r}") from None
            temp = _floats(temperature, "--temperature")
            if isinstance(temp, list) and len(temp) == 3:
                temp = {"start": temp[0], "end": temp[1], "tau": temp[2]}
            pay = _floats(payload, "--payload")
            if isinstance(pay, list):
                if len(pay) != 2:
                    raise typer.BadParameter("--payload: give M or LO,HI")
                pay = (pay[0], pay[1], "uniform")
            if from_fit is not None:
                from estcal.discrepancy.feedback import simulate_from_fit

                given = noise_pos or noise_rot or noise_joint or resolution
                res = simulate_from_fit(
                    from_fit, n_poses=n, strategy=strategy, measure=None if measure == "position" else measure,
                    noise=NoiseModel(position=noise_pos, orientation=noise_rot, joint=noise_joint,
                                     resolution=resolution, distribution=noise_dist) if given else None,
                    seed=seed, context={"temperature": temp, "payload": pay}, margin=margin, dt=dt,
                    record_approach=approach)
            else:
                errs = _load_errors(errors)
                if isinstance(errs, dict):
                    _check_errors(errs, nominal, errors)
                res = simulate(nominal, n_poses=n, strategy=strategy, measure=measure, errors=errs,
                               error_std=ErrorModel(angle=error_angle, length=error_length, offset=error_offset,
                                                    gain=error_gain),
                               effects=specs,
                               noise=NoiseModel(position=noise_pos, orientation=noise_rot, joint=noise_joint,
                                                resolution=resolution, distribution=noise_dist),
                               seed=seed, margin=margin, dt=dt, temperature=temp, payload=pay,
                               record_approach=approach, n_points=n_points, effect_params=eparams)
        except typer.BadParameter as exc:
            fail(exc.format_message())
        except (ValueError, KeyError, FileNotFoundError) as exc:
            fail(message(exc))
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
        console.print(table)
        for note in res.summary.notes:
            console.print("[yellow]note:[/yellow] " + escape(note))
        if json_path is not None:
            out = res.summary.to_dict()
            out["dataset"] = str(csv_path) if csv_path else None
            out["truth"] = str(truth_path) if truth_path else None
            write_json(json_path, out)

