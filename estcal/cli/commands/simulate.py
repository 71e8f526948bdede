"""``estcal simulate``: a simulated calibration dataset with its ground truth."""
from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from estcal.cli.common import fail, message
from estcal.io.jsonio import write_json


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
    from estcal.io.textinput import read_json, read_text

    if p.suffix.lower() in (".yaml", ".yml"):
        import yaml

        try:
            d = yaml.safe_load(read_text(p, "errors", ValueError))
        except yaml.YAMLError as exc:
            raise ValueError(f"{p}: invalid YAML ({' '.join(str(exc).split())})") from None
    else:
        d = read_json(p, "errors JSON", ValueError)
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


def register(app: typer.Typer) -> None:
    @app.command("simulate")
    def simulate_cmd(
        robot: str = typer.Option("puma560", "--robot", "-r",
                                  help="Built-in name, robot file (.yaml) or URDF (.urdf)."),
        n: int = typer.Option(50, "--n", "-n", help="Number of poses."),
        strategy: str = typer.Option("S4", help="Pose strategy: S1 (together), S2 (one joint at a time), "
                                                "S3 (one held), S4 (uniform random)."),
        measure: str = typer.Option("position", help="position | points | pose."),
        noise_pos: float = typer.Option(0.0, "--noise-pos", help="Position noise σ (m); half-width if uniform."),
        noise_rot: float = typer.Option(0.0, "--noise-rot", help="Orientation noise σ (rad); half-width if uniform."),
        noise_joint: float = typer.Option(0.0, "--noise-joint", help="Joint-reading noise σ (rad or m)."),
        resolution: float = typer.Option(0.0, "--resolution", help="Encoder resolution (rad or m); 0 = none."),
        noise_dist: str = typer.Option("gaussian", "--noise-dist", help="gaussian | uniform."),
        errors: str = typer.Option("random", help="random | none | JSON/YAML file {parameter: error}."),
        error_angle: float = typer.Option(1e-3, "--error-angle", help="σ of random angle errors (rad)."),
        error_length: float = typer.Option(1e-3, "--error-length", help="σ of random length errors (m)."),
        error_offset: float = typer.Option(1e-3, "--error-offset", help="σ of random joint-offset errors."),
        error_gain: float = typer.Option(0.0, "--error-gain", help="σ of random joint-gain errors."),
        effects: Optional[List[str]] = typer.Option(
            None, "--effects", "-e",
            help="Effect NAME[:JOINT,JOINT] (repeat, or separate with ';'), e.g. joint_compliance:j2,j3."),
        effect_param: Optional[List[str]] = typer.Option(
            None, "--effect-param", help="NAME=VALUE for an effect parameter, e.g. compliance_j2=2e-6 (repeat)."),
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
        json_path: Optional[Path] = typer.Option(None, "--json", help="Write the summary as JSON."),
        from_fit: Optional[Path] = typer.Option(
            None, "--from-fit", help="Diagnosis fit (estcal diagnose --json): simulate the robot as identified "
                                     "(geometric + named effects); --errors/--effects are ignored, the noise "
                                     "defaults to the fit's, --measure position means the fit's kind."),
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

        console = Console()
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
                res = simulate(nominal, n_poses=n, strategy=strategy, measure=measure, errors=_load_errors(errors),
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
        table = Table(title=f"estcal simulate — {res.summary.robot}", show_header=False)
        table.add_column("item", style="bold")
        table.add_column("value")
        for k, v in res.summary.rows():
            table.add_row(k, escape(v))
        if csv_path:
            table.add_row("dataset", str(csv_path))
        if truth_path:
            table.add_row("ground truth", str(truth_path))
        console.print(table)
        for note in res.summary.notes:
            console.print("[yellow]note:[/yellow] " + escape(note))
        if json_path is not None:
            out = res.summary.to_dict()
            out["dataset"] = str(csv_path) if csv_path else None
            out["truth"] = str(truth_path) if truth_path else None
            write_json(json_path, out)

