"""``estcal online``: recursive (Kalman) calibration of a dataset streamed row by row."""
from __future__ import annotations

import re
import sys
from pathlib import Path
from typing import Optional

import typer
from estcal.cli.units import deprecated_option, noise_pos_option, noise_rot_option
from estcal.base.jsonio import write_json

POSE_COLS = ("x", "y", "z", "qw", "qx", "qy", "qz")
_BINARY = re.compile("[\x00-\x08\x0b\x0c\x0e-\x1f]")  # never in CSV text (tab, LF, CR allowed)


def _row_dataset(header, values, robot, where, line, delimiter=",", allow_none: bool = False, header_line: int = 1):
    """One CSV row as a one-pose Dataset, through the loader's own checks
    (:func:`estcal.io.dataset.dataset_from_table`: header, numbers, units, ranges)."""
    from estcal.io.dataset import DatasetError, dataset_from_table
    from estcal.base.textinput import CsvTable

    ds = dataset_from_table(CsvTable(header, [values], [line], header_line, delimiter, where), robot)
    if ds.kind == "none" and not allow_none:
        raise DatasetError(f"{where}: no measurement columns (x,y,z / x1..zk / x,y,z,qw,qx,qy,qz)")
    return ds


def _lines(data: str, block: int = 1 << 20):
    """Lines of the input as they come, in bounded memory (a 10⁶-row file is never held whole).

    A file has been read and checked by the input layer already (folder, binary, encoding):
    here it is decoded block by block — UTF-8 with or without BOM, or UTF-16 with BOM — and
    split exactly as ``str.splitlines(keepends=True)`` splits the whole text (a block's last,
    possibly incomplete line, or a ``\r`` whose ``\n`` may start the next block, is carried
    over)."""
    if data == "-":
        yield from sys.stdin
        return
    import codecs

    with open(data, "rb") as fh:
        bom = fh.read(2)
    enc = "utf-16" if bom in (codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE) else "utf-8-sig"
    with open(data, encoding=enc, newline="") as fh:
        carry = ""
        while True:
            text = fh.read(block)
            if not text:
                break
            parts = (carry + text).splitlines(keepends=True)
            carry = parts.pop()
            yield from parts
        if carry:
            yield from carry.splitlines(keepends=True)


def _hold_lock(path, fail) -> None:
    """Lock ``path`` for this run (:class:`estcal.base.lock.RunLock`), released when the command ends."""
    from estcal.cli.common import on_exit
    from estcal.base.lock import LockedError, RunLock

    try:
        lock = RunLock(path, "--state").acquire()
    except LockedError as exc:
        fail(f"--state: {exc}")
    except OSError as exc:
        fail(f"--state {path}: cannot create its lock file ({exc.strerror or exc})")
    on_exit(lock.release)


def _check_free_identifiable(problem, where) -> None:
    """An explicit ``--free`` set must be identifiable from the whole file, as in ``estcal
    calibrate`` (a filter would otherwise print prior-only parameters and drifting
    combinations as estimates). Large files: the chunked R factor (same column relations)."""
    from estcal.cli.common import fail
    from estcal.estimate.lsq import UnidentifiableError, _DenseSystem, _ReducedSystem, check_identifiable
    from estcal.estimate.reduced import use_chunks

    pv = problem.params
    ck = use_chunks(problem)
    system = _DenseSystem(problem, pv.free_indices) if ck is None else _ReducedSystem(problem, pv.free_indices, ck)
    A = system.linear(pv.values)[0]
    try:
        check_identifiable(A, pv.free_names)
    except UnidentifiableError as exc:
        fail(f"--free: {where}: {exc}")


def register(app: typer.Typer) -> None:
    @app.command("online")
    def online_cmd(
        data: str = typer.Argument(..., help="Dataset CSV, or '-' to read rows from standard input as they come."),
        robot: str = typer.Option(..., "--robot", "-r", help="Built-in name, robot file (.yaml) or URDF."),
        free: Optional[str] = typer.Option(None, "--free", help="Comma-separated names/patterns to estimate "
                                           "(default: an identifiable set for a file, the robot's free mask for stdin)."),
        q_mm: float = typer.Option(0.0, "--q-mm", help="Process-noise std per row, in each parameter's milli-unit "
                                   "(mm, mrad, 10⁻³ for gains); 0 = constant parameters, > 0 = random walk / drift."),
        q_params: Optional[str] = typer.Option(None, "--q-params", help="Apply --q-mm only to these names/patterns."),
        filter_kind: str = typer.Option("ekf", "--filter", help="ekf or ukf (filterpy)."),
        method: Optional[str] = typer.Option(None, "--method", help="Measurement method (default: from the columns)."),
        sigma_p_mm: float = noise_pos_option(0.1),
        sigma_r_mrad: float = noise_rot_option(1.0),
        prior_std_mm: float = typer.Option(100.0, "--prior-std-mm", help="Prior std of every free parameter, in its "
                                           "milli-unit (mm, mrad, 10⁻³ for gains)."),
        old_q: Optional[float] = deprecated_option("--q"),
        old_sigma_p: Optional[float] = deprecated_option("--sigma-p"),
        old_sigma_r: Optional[float] = deprecated_option("--sigma-r"),
        old_prior_std: Optional[float] = deprecated_option("--prior-std"),
        every: int = typer.Option(10, "--every", help="Print a status line (or refresh the live table) every N rows; with N ≥ 100 and a file "
                              "as input, a progress bar is also drawn on a terminal."),
        live: bool = typer.Option(False, "--live", help="Show a live-updating table (terminal) instead of lines."),
        show: int = typer.Option(4, "--show", help="Parameters shown on each status line."),
        root: Optional[str] = typer.Option(None, help="URDF root link."),
        tip: Optional[str] = typer.Option(None, help="URDF tip link."),
        json_path: Optional[Path] = typer.Option(None, "--json", help="Write the final estimate, stds, innovation "
                                                 "tests and the printed history as JSON."),
        report: Optional[Path] = typer.Option(None, "--report", help="Folder for a report: estimate ± σ after "
                                              "every row, NIS per row with the innovation tests (PNG), tables and "
                                              "index.html."),
        state_path: Optional[Path] = typer.Option(None, "--state", help="Checkpoint file: the filter (x, P, Q, noise, "
                                                  "row, input SHA-256, options) written atomically every "
                                                  "--checkpoint-every rows and at exit; also a state for "
                                                  "`estcal next-pose --state`."),
        resume: Optional[Path] = typer.Option(None, "--resume", help="Continue from this checkpoint (same input and "
                                              "options; checkpoints keep going to it unless --state is given)."),
        checkpoint_every: int = typer.Option(100, "--checkpoint-every", help="Rows between checkpoints (count)."),
        throttle: float = typer.Option(0.0, "--throttle", help="Seconds to wait after each row (replay a file "
                                       "as a slow live stream)."),
    ) -> None:
        """Kalman-filter calibration, one row at a time: estimate, standard deviations and innovation statistics
        are printed as the rows arrive (mm, mrad; the JSON is SI)."""
        import csv

        from estcal.base.units import MILLI, display_unit
        from estcal.cli.units import resolve

        q = resolve(q_mm, MILLI, old_q, "--q", "--q-mm", "SI", 1.0, 0.0)
        sigma_p = resolve(sigma_p_mm, MILLI, old_sigma_p, "--sigma-p", "--noise-pos-mm", "m", 1.0, 0.1)
        sigma_r = resolve(sigma_r_mrad, MILLI, old_sigma_r, "--sigma-r", "--noise-rot-mrad", "rad", 1.0, 1.0)
        prior_std = resolve(prior_std_mm, MILLI, old_prior_std, "--prior-std", "--prior-std-mm", "SI", 1.0, 100.0)

        import numpy as np
        from rich.console import Console
        from rich.markup import escape
        from rich.table import Table

        from estcal.estimate.kalman import ParameterFilter, default_burn_in, process_noise
        from estcal.io.dataset import DatasetError
        from estcal.methods.base import NoiseModel, get_method, method_for_dataset
        from estcal.methods.problem import Problem, Term

        console = Console(stderr=False)
        err = Console(stderr=True)

        live_holder = []

        def fail(msg):
            for lv in live_holder:  # leave the terminal clean before the message
                lv.stop()
            err.print("[red]error:[/red] " + escape(str(msg)), soft_wrap=True)
            raise typer.Exit(2)

        try:
            try:
                from estcal.io.robotfile import load_robot

                rb = load_robot(robot, root=root, tip=tip)
            except ImportError:
                from estcal.kinematics.robots import get_builtin

                rb = get_builtin(robot)
        except (ValueError, KeyError, FileNotFoundError) as exc:
            fail(exc)
        noise = NoiseModel(sigma_p, sigma_r, known=True)
        from estcal.estimate._common import PER_POSE_METHODS
        from estcal.estimate.checkpoint import (CheckpointError, Journal, PrefixHasher, file_sha256,
                                                filter_checkpoint, load_checkpoint, option_differences,
                                                restore_filter, save_checkpoint)
        from estcal.estimate.innovation import GrowingArray

        if checkpoint_every < 1:
            fail(f"--checkpoint-every must be ≥ 1, got {checkpoint_every}")
        if throttle < 0:
            fail(f"--throttle must be ≥ 0 s, got {throttle}")
        # the options that change the estimates (SI): a resumed run must use the same ones
        run_options = {"--robot": robot, "--root": root, "--tip": tip, "--free": free, "q (SI)": q,
                       "--q-params": q_params, "--filter": filter_kind, "--method": method, "noise-pos (m)": sigma_p,
                       "noise-rot (rad)": sigma_r, "prior-std (SI)": prior_std}
        if state_path is not None:  # a folder, an input file, an unwritable place: before the work
            from estcal.cli.checks import check_outputs

            check_outputs({"--state": state_path}, [Path(data)] if data != "-" else [])
        if resume is not None and resume.is_dir():
            fail(f"--resume {resume}: is a folder — give the checkpoint file written by --state")
        for held in {p for p in (state_path, resume) if p is not None}:  # one writer per checkpoint
            _hold_lock(held, fail)
        saved = None
        if resume is not None:
            try:
                saved = load_checkpoint(resume)
            except CheckpointError as exc:
                fail(f"--resume: {exc}")
            diff = option_differences(saved["options"], run_options)
            if diff:
                fail(f"--resume {resume}: the options differ from the checkpointed run (SI values): "
                     f"{'; '.join(diff)} — give the same options to continue it")
            if state_path is None:
                state_path = resume
        if resume is None and state_path is not None and state_path.exists():
            fail(f"--state {state_path}: the file exists (a previous run's checkpoint?) — continue it with "
                 f"--resume {state_path}, or remove it / choose another path")

        try:
            meth = get_method(method) if method else None
        except ValueError as exc:
            fail(exc)
        if meth is not None and meth.name not in PER_POSE_METHODS:
            fail(f"method {meth.name!r} compares several rows (groups/pairs); `estcal online` streams one row "
                 f"at a time and supports {', '.join(PER_POSE_METHODS)} — use `estcal calibrate --method kalman`")
        ds_all = None
        n_total = None  # data rows of a file (for the progress bar)
        if data != "-":
            # a file is checked as a whole first (the loader's unit, range, duplicate and spread
            # checks), so that the stream below never runs on data the batch commands refuse
            from estcal.cli.common import check_distinct_poses
            from estcal.io.dataset import load_dataset

            try:
                ds_all = load_dataset(data, rb)
            except (ValueError, FileNotFoundError) as exc:
                fail(exc)
            check_distinct_poses(ds_all)
            from estcal.cli.common import warn_datasets

            warn_datasets([ds_all])  # the same warnings as the batch commands
            n_total = ds_all.n
        if saved is not None:
            names_pat = list(saved["parameters"])  # the free set the run started with (a file may have grown)
        elif free:
            names_pat = [s.strip() for s in free.split(",") if s.strip()]
        elif ds_all is not None:
            from estcal.estimate._common import identifiable_free

            try:
                prob_all = Problem(rb, [(meth, ds_all, noise)])
                names_pat = identifiable_free(prob_all)
            except (ValueError, FileNotFoundError) as exc:
                fail(exc)
            del prob_all
        else:
            names_pat = rb.params.free_names
        try:
            rb = rb.copy(rb.params.with_free(names_pat))
        except KeyError as exc:
            fail(f"--free: {exc}" if free else exc)
        if free and saved is None and ds_all is not None:
            _check_free_identifiable(Problem(rb, [(meth, ds_all, noise)]), data)
        del ds_all  # checked; the rows are streamed below
        pv = rb.params
        fidx = pv.free_indices
        names = pv.free_names
        units = [display_unit(n, rb) for n in names]  # printed in mm / mrad (SI in the JSON)
        try:
            Q = process_noise(names, {p.strip(): q for p in q_params.split(",")} if q_params else q)
        except ValueError as exc:
            fail(exc)
        P0 = np.eye(len(names)) * prior_std ** 2
        try:
            flt = ParameterFilter(pv.values, fidx, P0, Q, kind=filter_kind, names=names)
            history = restore_filter(flt, saved, resume) if saved is not None else []
            journal = None
            if state_path is not None:
                journal = Journal.resume(state_path, saved, resume) if saved is not None else Journal.start(state_path)
        except (ValueError, CheckpointError) as exc:
            fail(exc)
        except OSError as exc:
            fail(f"--state {state_path}: cannot write its journal ({exc.strerror or exc})")
        input_sha = file_sha256(data) if data != "-" else None
        hasher = PrefixHasher()
        where = "<stdin>" if data == "-" else data

        def numbered():
            src = enumerate(_lines(data), start=1)
            while True:
                try:
                    ln, text = next(src)
                    bad = _BINARY.search(text)
                    if bad:
                        fail(f"{where}, line {ln}, column {bad.start() + 1}: control character "
                             f"0x{ord(bad.group()):02x} — binary data, not CSV text")
                    hasher.update(text.encode("utf-8"))  # the consumed prefix, named in checkpoints
                    yield ln, text
                except StopIteration:
                    return
                except UnicodeDecodeError:
                    fail(f"{where}: input is not UTF-8 text — send the CSV as UTF-8")

        rows = numbered()
        header_line = 0
        for header_line, first in rows:
            if first.strip():
                break
        else:
            fail(f"{where}: empty input (expected a header row)")
        from estcal.base.textinput import sniff_delimiter

        first = first.lstrip("\ufeff")
        delim = sniff_delimiter(first)
        header = [h.strip() for h in next(csv.reader([first], delimiter=delim))]
        trace_x = GrowingArray(float, len(names))  # every row's estimate and std, for --report
        trace_s = GrowingArray(float, len(names))
        burn = None
        rows_done, last_line = 0, header_line
        skip = 0
        if saved is not None:
            burn = saved["burn"]
            skip = int(saved["rows"])

        def checkpoint(finished=False):
            if state_path is None or rows_done < skip:  # still replaying the checkpointed rows: keep it
                return
            ptr = journal.append(flt.monitor, history)  # first the journal, then the checkpoint naming it
            save_checkpoint(state_path, filter_checkpoint(
                flt, options=run_options, rows=rows_done, line=last_line, hasher=hasher, input_sha256=input_sha,
                burn=burn, journal=ptr, finished=finished))
        shown = list(range(min(show, len(names))))

        def live_table():
            run = flt.monitor.running(burn or flt.n_steps)
            tb = Table(title=f"{rb.name}: {flt.n_steps} rows, NIS/row {run['nis_per_row']:.3f}, "
                             f"trace P {np.trace(flt.f.P):.3g}")
            for c in ("parameter", "estimate", "std", "Δ from nominal", "unit"):
                tb.add_column(c, justify="right" if c not in ("parameter", "unit") else "left")
            x, sd = flt.x, flt.std
            for i, n in enumerate(names):
                u, f = units[i]
                tb.add_row(n, f"{x[i] * f:.6g}", f"{sd[i] * f:.3g}", f"{(x[i] - pv.values[fidx[i]]) * f:.3g}", u)
            return tb

        live_ctx = None
        if live:
            from rich.live import Live

            live_ctx = Live(Table(title="waiting for rows"), console=console, refresh_per_second=4)
            live_ctx.start()
            live_holder.append(live_ctx)
        console.print(f"estcal online: {rb.name}, {len(names)} free parameters, filter {filter_kind}, "
                      f"q = {q / MILLI:g} mm / mrad{' on ' + q_params if q_params else ''}; reading {where}"
                      + (f"; resuming after row {skip} (line {saved['line']}) of {resume}" if saved else ""))
        import signal
        import time

        def _term(signum, frame):  # SIGTERM: leave through the checkpoint below, like Ctrl-C
            raise KeyboardInterrupt

        try:
            old_term = signal.signal(signal.SIGTERM, _term)
        except ValueError:  # not the main thread (e.g. an embedding application)
            old_term = None

        def refuse_input(msg):
            fail(f"--resume {resume}: {msg} — resume needs the input the checkpointed run read (its first "
                 f"{saved['input_bytes']} bytes, {skip} data rows, unchanged)")

        def check_prefix():
            if hasher.n != saved["input_bytes"] or hasher.hexdigest() != saved["input_sha256_prefix"]:
                refuse_input(f"{where} differs from the checkpointed input (SHA-256 of the rows already "
                             f"processed does not match)")

        def stop(msg):  # a bad row: keep what was computed before it
            checkpoint()
            fail(msg)

        from estcal.base.progress import progress

        # a bar (rows done, rate, time left) on a terminal when the status lines are sparse — with
        # a line every few rows those lines already show the progress, and the live table its count
        quiet = live or n_total is None or every < 100
        bar = progress(total=n_total, desc="online", unit="row", enabled=False if quiet else None)
        try:
            if saved is not None and skip == 0:
                check_prefix()
            for ln, line in rows:
                if not line.strip():
                    continue
                bar.update(1)
                if rows_done < skip:  # already in the checkpoint: hashed, not processed again
                    rows_done, last_line = rows_done + 1, ln
                    if rows_done == skip:
                        check_prefix()
                    continue
                try:
                    vals = next(csv.reader([line], delimiter=delim))
                except csv.Error as exc:
                    stop(f"{where}, line {ln}: not a valid CSV line ({exc})")
                try:
                    ds = _row_dataset(header, vals, rb, where, ln, delim, allow_none=meth is not None,
                                      header_line=header_line)
                    m = meth or method_for_dataset(ds, rb)
                    sub = Problem.__new__(Problem)
                    sub.robot = rb
                    sub.terms = [Term(m, ds, noise)]
                    step = flt.step(sub)
                except (DatasetError, ValueError, np.linalg.LinAlgError) as exc:
                    stop(exc)
                rows_done, last_line = rows_done + 1, ln
                if report is not None:
                    trace_x.append(flt.f.x)
                    trace_s.append(flt.std)
                if burn is None and flt.n_rows >= 2 * len(names):
                    burn = flt.n_steps
                k = flt.n_steps
                if k % every == 0:
                    run = flt.monitor.running(burn or k)
                    x, s = flt.x, flt.std
                    history.append({"row": k, "line": ln, "nis": step.nis, "nis_per_row": run["nis_per_row"],
                                    "trace_P": float(np.trace(flt.f.P)), "estimate": x.tolist(),
                                    "std": s.tolist()})
                    if live_ctx is not None:
                        live_ctx.update(live_table())
                    else:
                        par = "  ".join(f"{names[i]}={x[i] * units[i][1]:.6g}±{s[i] * units[i][1]:.2g}"
                                        f"{(' ' + units[i][0]) if units[i][0] else ''}" for i in shown)
                        avg = run["nis_per_row"]  # undefined until the burn-in is over
                        avg = f"{avg:.3f}" if np.isfinite(avg) else "— (burn-in)"
                        console.print(f"row {k:5d}  NIS {step.nis:7.2f}/{step.y.size}  NIS/row(avg) {avg}  {par}",
                                      soft_wrap=True)
                if rows_done % checkpoint_every == 0:
                    checkpoint()
                if throttle:
                    time.sleep(throttle)
            if rows_done < skip:
                refuse_input(f"{where} has {rows_done} data rows, fewer than the {skip} already processed")
        except KeyboardInterrupt:
            checkpoint()
            if live_ctx is not None:
                live_ctx.stop()
            if state_path is not None:
                err.print(f"interrupted after row {rows_done} (line {last_line}); checkpoint {state_path} — "
                          f"continue with --resume {state_path}")
            raise typer.Exit(130)
        finally:
            bar.close()
            if old_term is not None:
                signal.signal(signal.SIGTERM, old_term)
        checkpoint(finished=True)
        if live_ctx is not None:
            live_ctx.stop()
        if flt.n_steps == 0:
            fail(f"{where}: no data rows")
        x, s = flt.x, flt.std
        table = Table(title=f"estimate after {flt.n_steps} rows")
        for c in ("parameter", "nominal", "estimate", "std", "unit"):
            table.add_column(c, justify="right" if c not in ("parameter", "unit") else "left")
        for i, n in enumerate(names):
            u, f = units[i]
            table.add_row(n, f"{pv.values[fidx[i]] * f:.6g}", f"{x[i] * f:.6g}", f"{s[i] * f:.3g}", u)
        console.print(table)
        bi = default_burn_in(flt.monitor.dims, len(names))
        try:
            tests = flt.monitor.tests(burn_in=bi).to_dict()
            from estcal.estimate.innovation import InnovationTests

            console.print(str(InnovationTests(**tests)))
        except ValueError as exc:
            tests = {"error": str(exc)}
            console.print(f"innovation tests: {exc}")
        out = {"robot": rb.name, "input": where, "filter": filter_kind, "q": q, "q_params": q_params,
               "n_rows": flt.n_steps, "parameters": {n: {"estimate": float(x[i]), "std": float(s[i]),
                                                         "nominal": float(pv.values[fidx[i]])}
                                                     for i, n in enumerate(names)},
               "covariance": flt.P.tolist(), "innovation": tests, "history": history}
        if json_path is not None:
            write_json(json_path, out)
            console.print(f"JSON -> {json_path}")
        if report is not None:
            from estcal.report.online import online_report
            from estcal.base.units import display_unit

            online_report(report, names, pv.values[fidx], trace_x.values, trace_s.values, flt.monitor.nis, flt.monitor.dims, tests,
                          unit=lambda n: display_unit(n, rb), title=f"estcal online — {rb.name}, {where}",
                          result_dict=out)
            console.print(f"report -> {report}/index.html")
