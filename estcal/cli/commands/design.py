"""``estcal design``: an optimal measurement plan for a robot, method and noise model.

Prints and (``--json PATH``) saves the plan (joint readings), its criterion,
every other criterion, the predicted parameter standard deviations
((JᵀWJ)⁻¹, the covariance the estimators report) and the distribution of the
criterion over random plans of the same size.

JSON keys: ``robot``, ``method``, ``sigma_mm``, ``free`` (names), ``criterion``,
``plan`` (:meth:`Plan.to_dict`: ``readings_rad``, ``readings_deg``, ``value``, …),
``criteria`` (all criteria of the plan, ``param_std`` in SI units),
``rho0_mm`` (predicted RMS position error at each test pose), ``test_poses_rad``,
``baseline`` (:meth:`BaselineStats.to_dict`: min/mean/max/percentiles),
``beats_random`` (plan better than the best random plan), ``accuracy_map`` (with ``--map N``:
``q``, ``xyz`` (m), ``std`` (m) per pose and a ``summary``; ``--report DIR`` implies ``--map 500``).
"""
from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer
from estcal.cli.units import deprecated_option, noise_pos_option, noise_rot_option
from estcal.base.jsonio import write_json


def register(app: typer.Typer) -> None:
    @app.command("design")
    def design_cmd(
        robot: str = typer.Option(..., "--robot", "-r", help="Built-in name, robot file (.yaml) or URDF."),
        method: str = typer.Option("position", "--method", help="position, pose or points."),
        n: int = typer.Option(..., "--n", help="Number of poses m in the plan."),
        criterion: str = typer.Option("D", "--criterion", "-c",
                                      help="D, A, E, G, O1..O5, cond (κ(J)), cond_JtJ, test-pose, test-pose-max."),
        test_pose: Optional[List[str]] = typer.Option(
            None, "--test-pose", help="Test pose 'q1,q2,...' (revolute in deg, prismatic in mm); repeatable. "
                                      "Default (when needed): mid-range of every joint."),
        candidates: Optional[Path] = typer.Option(None, "--candidates",
                                                  help="CSV of candidate readings (rad / m; header optional)."),
        degrees: bool = typer.Option(False, "--degrees", help="Candidate CSV revolute columns are in degrees."),
        algorithm: str = typer.Option("fedorov", "--algorithm",
                                      help="greedy, fedorov, detmax (discrete) or continuous."),
        n_candidates: int = typer.Option(2000, "--n-candidates", help="Random candidates when no CSV is given."),
        restarts: int = typer.Option(4, "--restarts", help="Restarts (discrete) / starts (continuous)."),
        sigma_mm: float = noise_pos_option(0.1),
        sigma_rot_mrad: float = noise_rot_option(1.0, ", pose method"),
        old_sigma: Optional[float] = deprecated_option("--sigma"),
        old_sigma_rot: Optional[float] = deprecated_option("--sigma-rot"),
        free: Optional[str] = typer.Option(None, "--free",
                                           help="Free parameters (comma-separated names/patterns); "
                                                "default: an identifiable subset (offsets first)."),
        random_plans: int = typer.Option(1000, "--random-plans", help="Random plans in the baseline."),
        map_n: int = typer.Option(0, "--map", help="Accuracy map: expected position error over N random poses "
                                                 "within the joint limits (0 = off)."),
        map_box: Optional[str] = typer.Option(None, "--map-box",
                                              help="Restrict the map to a tool-position box "
                                                   "'xmin,ymin,zmin,xmax,ymax,zmax' (mm)."),
        seed: int = typer.Option(0, "--seed"),
        scheduler: str = typer.Option("processes", "--scheduler", help="Where the continuous starts run: "
                                      "serial | processes | local (Dask LocalCluster) | tcp://host:8786."),
        workers: Optional[int] = typer.Option(None, "--workers", help="Worker processes (processes / local)."),
        json_path: Optional[Path] = typer.Option(None, "--json", help="Write the results as JSON."),
        report: Optional[Path] = typer.Option(None, "--report", help="Folder for a report: plan, criteria, "
                                              "random-plan histogram, predicted error over the workspace (PNG) "
                                              "and index.html. Implies --map 500 unless --map is given."),
    ) -> None:
        """Optimise which poses to measure (plan of m poses) and compare with random plans."""
        import numpy as np
        from rich.console import Console
        from rich.markup import escape

        from estcal.design._cli import default_test_pose, format_readings, parse_free, parse_poses
        from estcal.design.criteria import CRITERIA, larger_is_better, normalise_criterion
        from estcal.design.model import DesignModel, resolve_robot
        from estcal.design.plans import (evaluate_plan, load_candidates, optimise_continuous,
                                         optimise_discrete, random_baseline)

        from estcal.cli.units import resolve

        sigma_mm = resolve(sigma_mm, 1.0, old_sigma, "--sigma", "--noise-pos-mm", "mm", 1.0, 0.1)
        sigma_rot_mrad = resolve(sigma_rot_mrad, 1.0, old_sigma_rot, "--sigma-rot", "--noise-rot-mrad", "mrad", 1.0,
                                 1.0)
        console = Console()
        if report is not None and map_n <= 0:
            map_n = 500  # the report's workspace figure needs an accuracy map
        try:
            crit = normalise_criterion(criterion)
            rb = resolve_robot(robot)
            names = parse_free(free, rb, method)
            model = DesignModel(rb, method, names, sigma=sigma_mm * 1e-3,
                                sigma_rot=sigma_rot_mrad * 1e-3 if method == "pose" else None)
            need = -(-model.p // model.rows_per_pose)  # ceil: poses for as many equations as parameters
            if n < need and model.prior_information is None:
                from estcal.cli.common import refuse

                refuse(f"--n {n}: a plan of {n} poses gives {n * model.rows_per_pose} equations for {model.p} free "
                       f"parameters — the information matrix is singular (every criterion infinite or zero); use "
                       f"--n {need} or more, or fewer --free parameters")
            q_test = parse_poses(test_pose, rb)
            if q_test is None and CRITERIA[crit][1]:
                q_test = default_test_pose(rb)
            cand = None if candidates is None else load_candidates(candidates, rb, degrees)
            if cand is not None and model.prior_information is None:
                # a plan drawn from candidates can determine no more than the candidates together
                J = model.jacobian(cand).reshape(-1, model.p)
                scale = np.linalg.norm(J, axis=0)
                r = int(np.linalg.matrix_rank(J / np.where(scale > 0, scale, 1.0))) if J.size else 0
                if r < model.p:
                    from estcal.cli.common import refuse

                    n_distinct = len(np.unique(np.asarray(cand), axis=0))
                    refuse(f"--candidates {candidates}: its {len(cand)} poses ({n_distinct} distinct) determine "
                           f"only {r} of the {model.p} free parameters — every plan drawn from them has a singular "
                           f"information matrix; give more and better-spread candidates, or fewer --free parameters")
            if algorithm == "continuous":
                if cand is not None:
                    raise ValueError("--candidates applies to the discrete algorithms, not 'continuous'")
                plan = optimise_continuous(model, n, crit, n_starts=restarts, rng=seed, q_test=q_test,
                                           scheduler=scheduler if restarts > 1 else "serial", n_workers=workers,
                                           prescreen=200)
            else:
                plan = optimise_discrete(model, n, crit, candidates=cand, n_candidates=n_candidates,
                                         algorithm=algorithm, restarts=restarts, rng=seed, q_test=q_test)
            crits = evaluate_plan(model, plan.readings, q_test=q_test)
            base = random_baseline(model, n, crit, n_plans=random_plans, rng=seed + 1, q_test=q_test,
                                   keep_values=report is not None)
            amap = None
            if map_n > 0:
                from estcal.design.model import ToolBox

                box = None
                if map_box:
                    v = [float(x) * 1e-3 for x in map_box.split(",")]
                    if len(v) != 6:
                        raise ValueError("--map-box needs 6 numbers xmin,ymin,zmin,xmax,ymax,zmax (mm)")
                    box = ToolBox(rb, v[:3], v[3:])
                amap = model.accuracy_map(model.covariance(plan.readings), n=map_n, rng=seed + 2, constraint=box)
        except (ValueError, KeyError, FileNotFoundError, np.linalg.LinAlgError) as exc:
            from estcal.cli.common import fail, message

            fail(message(exc))
        better = plan.value > base.max if larger_is_better(crit) else plan.value < base.min
        console.print(f"robot {rb.name}, method {method}, σ = {sigma_mm} mm, {model.p} free parameters")
        console.print(f"plan ({plan.method}, m = {plan.m}): {crit} = {plan.value:.6g}   [{CRITERIA[crit][2]}]")
        console.print("joint readings (" + ", ".join(rb.joint_names) + "):")
        for line in format_readings(plan.readings, rb):
            console.print("  " + line)
        console.print(escape(str(crits)))
        rho = None
        if q_test is not None:
            J0 = model.position_jacobian(q_test)
            C = model.covariance(plan.readings)
            rho = np.sqrt(np.einsum("tap,pq,taq->t", J0, C, J0)) * 1e3
            console.print("predicted RMS position error at the test pose(s) (mm): "
                          + ", ".join(f"{v:.5g}" for v in rho))
        from estcal.base.units import display_unit

        console.print("predicted parameter std:")
        for k, v in crits.param_std.items():
            u, f = display_unit(k, rb)
            console.print(f"  {k:<14}{v * f:.4g} {u}")
        console.print(escape(str(base)))
        if amap is not None:
            console.print(escape(str(amap)))
        console.print(f"optimised plan {'beats' if better else 'does NOT beat'} the best of "
                      f"{base.n_plans} random plans")
        out = {"robot": rb.name, "method": method, "sigma_mm": sigma_mm, "free": names, "criterion": crit,
               "plan": plan.to_dict(), "criteria": crits.to_dict(),
               "rho0_mm": None if rho is None else rho.tolist(),
               "test_poses_rad": None if q_test is None else q_test.tolist(),
               "baseline": base.to_dict(), "beats_random": bool(better),
               "accuracy_map": None if amap is None else amap.to_dict()}
        if json_path is not None:
            write_json(json_path, out)
            console.print(f"wrote {json_path}")
        if report is not None:
            from estcal.report.design import design_report
            from estcal.base.units import display_unit

            design_report(report, model, plan, crits, base, amap, rho, q_test, larger_is_better=larger_is_better(crit),
                          unit=lambda nm: display_unit(nm, rb), title=f"estcal design — {rb.name}",
                          result_dict=out)
            console.print(f"report: {report}/index.html")
