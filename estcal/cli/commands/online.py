"""``estcal online``: recursive (Kalman) calibration of a stream of CSV rows.

A thin user of :class:`estcal.workflows.online.OnlineCalibrator`: the rows are read in chunks
(:class:`~estcal.io.stream.CsvStream`), given to ``update``, and the status lines, the
final table, the innovation tests, the JSON and the report are printed from what it returns.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from estcal.cli.app import command
from estcal.cli.options import (deprecated_option, free_option, json_option, map_option, measure_option,
                                method_option, noise_pos_option, noise_rot_option, report_option, robot_option,
                                root_option, tip_option)

__all__ = ["online"]

#: data rows per chunk read from the input (besides the cuts at checkpoint rows)
CHUNK_ROWS = 1024


@command("online")
def online(
    data: str = typer.Argument(..., help="Dataset CSV, or '-' to read rows from standard input as they come."),
    robot: str = robot_option(),
    free: Optional[str] = free_option("Comma-separated names/patterns to estimate (default: an identifiable set "
                                      "for a file, the robot's free mask for stdin)."),
    q_mm: float = typer.Option(0.0, "--q-mm", help="Process-noise std per row, in each parameter's milli-unit "
                               "(mm, mrad, 10⁻³ for gains); 0 = constant parameters, > 0 = random walk / drift."),
    q_params: Optional[str] = typer.Option(None, "--q-params", help="Apply --q-mm only to these names/patterns."),
    filter_kind: str = typer.Option("ekf", "--filter", help="ekf or ukf (filterpy)."),
    measure: Optional[str] = measure_option(help="What was measured: position, pose, points (default: from the "
                                                 "columns)."),
    method: Optional[str] = method_option(),
    sigma_p_mm: float = noise_pos_option(0.1),
    sigma_r_mrad: float = noise_rot_option(1.0),
    prior_std_mm: float = typer.Option(100.0, "--prior-std-mm", help="Prior std of every free parameter, in its "
                                       "milli-unit (mm, mrad, 10⁻³ for gains)."),
    old_q: Optional[float] = deprecated_option("--q"),
    old_sigma_p: Optional[float] = deprecated_option("--sigma-p"),
    old_sigma_r: Optional[float] = deprecated_option("--sigma-r"),
    old_prior_std: Optional[float] = deprecated_option("--prior-std"),
    relinearize: Optional[str] = typer.Option(None, "--relinearize", help="Rows linearised at one estimate: "
                                              "'auto' (default: row by row first, then segments of up to 256 rows, "
                                              "vectorised) or N (1 = the classical row-by-row EKF)."),
    every: int = typer.Option(10, "--every", help="Print a status line (or refresh the live table) every N rows; with N ≥ 100 and a file "
                              "as input, a progress bar is also drawn on a terminal."),
    live: bool = typer.Option(False, "--live", help="Show a live-updating table (terminal) instead of lines."),
    show: int = typer.Option(4, "--show", help="Parameters shown on each status line."),
    root: Optional[str] = root_option(),
    tip: Optional[str] = tip_option(),
    column_map: Optional[Path] = map_option(),
    json_path: Optional[Path] = json_option("Write the final estimate, stds, innovation tests and the printed "
                                            "history as JSON (SI)."),
    report: Optional[Path] = report_option("Folder for a report: estimate ± σ after every row, NIS per row with "
                                           "the innovation tests (PNG), tables and index.html."),
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
    """Kalman-filter calibration of rows as they arrive: estimate, standard deviations and innovation
    statistics are printed as the rows come in (mm, mrad; the JSON is SI)."""
    from estcal.cli.common import fail
    from estcal.base.units import MILLI
    from estcal.cli.units import resolve

    q = resolve(q_mm, MILLI, old_q, "--q", "--q-mm", "SI", 1.0, 0.0)
    sigma_p = resolve(sigma_p_mm, MILLI, old_sigma_p, "--sigma-p", "--noise-pos-mm", "m", 1.0, 0.1)
    sigma_r = resolve(sigma_r_mrad, MILLI, old_sigma_r, "--sigma-r", "--noise-rot-mrad", "rad", 1.0, 1.0)
    prior_std = resolve(prior_std_mm, MILLI, old_prior_std, "--prior-std", "--prior-std-mm", "SI", 1.0, 100.0)
    from estcal.cli.options import estimator_and_measure

    _, measure = estimator_and_measure(method, None, measure, means="measure")
    if checkpoint_every < 1:
        fail(f"--checkpoint-every must be ≥ 1, got {checkpoint_every}")
    if throttle < 0:
        fail(f"--throttle must be ≥ 0 s, got {throttle}")
    rel = _relinearize(relinearize)
    options = {"free": free, "q": {p.strip(): q for p in q_params.split(",") if p.strip()} if q_params else q,
               "filter": filter_kind, "measure": measure, "noise": (sigma_p, sigma_r), "prior_std": prior_std,
               "relinearize": rel, "root": root, "tip": tip, "column_map": column_map}
    with _errors():
        run = _Run(data, robot, options, every, state_path, resume, report)
        run.stream(checkpoint_every, throttle, live, show)
        run.finish(json_path, report)


def _default_set(robot, ds, file_set, options, path):
    """The default free set of a file: the measurement's identifiable set (what ``OnlineCalibrator(robot)``
    estimates, :func:`estcal.workflows.online.default_free_set`); when the file identifies fewer
    parameters (degenerate poses), its own set, with a warning naming what is lost."""
    from estcal.cli.common import warn
    from estcal.workflows.online import default_free_set

    generic = default_free_set(robot, ds, options["measure"], options["noise"])
    if set(file_set) == set(generic):
        return generic
    lost = [n for n in generic if n not in file_set]
    warn(f"{path}: these rows identify {len(file_set)} of the {len(generic)} parameters the measurement identifies "
         f"on generic poses (lost: {', '.join(lost[:8])}{' …' if len(lost) > 8 else ''}) — the filter estimates the "
         f"{len(file_set)}; degenerate poses (a joint barely moved?)")
    return file_set


def _relinearize(text):
    if text is None or text == "auto":
        return None if text is None else "auto"
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        from estcal.cli.common import fail

        fail(f"--relinearize {text}: give 'auto' or an integer ≥ 1 (rows per linearisation)")
    return n


class _errors:
    """Errors of the workflow → ``error:`` lines and exit codes (2 input, 3 numerical refusal)."""

    def __enter__(self):
        return self

    def __exit__(self, typ, exc, tb):
        if exc is None or isinstance(exc, (typer.Exit, KeyboardInterrupt, SystemExit)):
            return False
        import numpy as np

        from estcal.cli.common import fail, message, refuse
        from estcal.base.errors import NumericalRefusal

        if isinstance(exc, NumericalRefusal):
            refuse(message(exc))
        if isinstance(exc, (ValueError, KeyError, FileNotFoundError, np.linalg.LinAlgError)):
            fail(message(exc))
        return False


class _Signals:
    """SIGTERM and Ctrl-C leave through the checkpoint (KeyboardInterrupt), but never in the middle
    of an update: there they wait until it is done."""

    def __enter__(self):
        import signal

        self.pending, self._busy, self.old = False, False, {}
        for s in (signal.SIGTERM, signal.SIGINT):
            try:
                self.old[s] = signal.signal(s, self._handle)
            except ValueError:  # not the main thread (e.g. an embedding application)
                pass
        return self

    def _handle(self, signum, frame):
        if self._busy:
            self.pending = True
        else:
            raise KeyboardInterrupt

    def busy(self):
        import contextlib

        @contextlib.contextmanager
        def block():
            self._busy = True
            try:
                yield
            finally:
                self._busy = False
            if self.pending:
                raise KeyboardInterrupt

        return block()

    def __exit__(self, *exc):
        import signal

        for s, h in self.old.items():
            signal.signal(s, h)
        return False


class _Run:
    """One ``estcal online`` run: the calibrator, the input stream, the printing."""

    def __init__(self, data, robot, options, every, state_path, resume, report):
        from rich.console import Console

        from estcal.cli.checks import check_outputs
        from estcal.cli.common import fail, on_exit
        from estcal.estimate.innovation import GrowingArray

        self.console, self.err = Console(stderr=False), Console(stderr=True)
        self.data, self.every, self.live_ctx, self.resume = data, every, None, resume
        self.where = "<stdin>" if data == "-" else data
        if state_path is not None:  # a folder, an input file, an unwritable place: before the work
            check_outputs({"--state": state_path}, [Path(data)] if data != "-" else [])
        if resume is not None and resume.is_dir():
            fail(f"--resume {resume}: is a folder — give the checkpoint file written by --state")
        if resume is None and state_path is not None and state_path.exists():
            from estcal.base.lock import LockedError, RunLock

            try:  # a running run's checkpoint is named as such
                RunLock(state_path, "--state").acquire().release()
            except LockedError as exc:
                fail(f"--state {exc}")
            fail(f"--state {state_path}: the file exists (a previous run's checkpoint?) — continue it with "
                 f"--resume {state_path}, or remove it / choose another path")
        self.ds_all = self._check_file(robot, options) if data != "-" else None
        self.cal = self._calibrator(robot, options, resume, every)
        on_exit(self.cal.close)
        self.state_path = state_path if state_path is not None else resume
        p = len(self.cal.names)
        self.trace = (GrowingArray(float, p), GrowingArray(float, p)) if report is not None else None

    def _check_file(self, robot, options):
        from estcal.io.robotfile import load_robot
        from estcal.workflows.online import check_file

        self.rb = load_robot(robot, root=options["root"], tip=options["tip"])
        ds = check_file(self.data, self.rb, column_map=options["column_map"])
        from estcal.workflows.check import screen

        screen([ds], self.rb)  # the data screening's findings, as calibrate prints them (docs/dataset.md)
        return ds

    def _calibrator(self, robot, options, resume, every):
        from estcal.cli.common import fail, message
        from estcal.estimate.checkpoint import CheckpointError
        from estcal.workflows.online import OnlineCalibrator, file_free_set

        rb = robot if self.ds_all is None else self.rb
        if resume is not None:
            given = {k: v for k, v in options.items() if k != "free" or v is not None}
            try:
                return OnlineCalibrator.resume(resume, rb, history_every=every, **given)
            except CheckpointError as exc:
                fail(f"--resume {exc}")
        opts = dict(options, relinearize=options["relinearize"] or "auto")
        if self.ds_all is not None:
            try:
                opts["free"] = file_free_set(self.rb, self.ds_all, options["free"], options["measure"],
                                             options["noise"])
            except KeyError as exc:
                fail(f"--free: {message(exc)}")
            except ValueError as exc:
                fail(f"--free: {self.data}: {exc}" if options["free"] else exc)
            if options["free"] is None:
                opts["free"] = _default_set(self.rb, self.ds_all, opts["free"], options, self.data)
        elif options["free"] is None:  # standard input: the set of the measurement its header names
            from estcal.io.robotfile import load_robot
            from estcal.workflows.online import CsvStream, default_free_set

            rb = load_robot(robot, root=options["root"], tip=options["tip"])
            self._src = CsvStream("-", rb, cut=lambda n: self._cut(n), measure=options["measure"],
                                  column_map=options["column_map"])
            try:
                layout = self._src.layout()
            except ValueError:  # a header that does not read: the stream names it (binary rows first, as before)
                layout = None
            opts["free"] = (default_free_set(rb, layout, options["measure"], options["noise"])
                            if layout is not None and layout.kind != "none" else rb.params.free_names)
        try:
            cal = OnlineCalibrator(rb, history_every=every, **opts)
        except KeyError as exc:
            fail(f"--free: {message(exc)}" if options["free"] else message(exc))
        cal.options["--robot"], cal.options["--free"] = robot, options["free"]  # as the user gave them
        return cal

    def _save(self, position, finished=False):
        from estcal.estimate.checkpoint import CheckpointError

        if self.src.rows < self.skip:  # still reading the checkpointed rows: keep the checkpoint as it is
            return
        try:
            self.cal.save(self.state_path, position=position, finished=finished)
        except CheckpointError as exc:
            self._fail(f"--state {exc}")

    # ------------------------------------------------------------------ stream
    def stream(self, checkpoint_every, throttle, live, show):
        from estcal.estimate.checkpoint import CheckpointError
        from estcal.base.progress import progress
        from estcal.workflows.online import CsvStream

        cal = self.cal
        saved = getattr(cal, "checkpoint", None)
        self.skip = skip = int(saved["rows"]) if saved else 0
        self.every_ck, self.last_ck = checkpoint_every, skip

        def cut(n):  # chunks end where the filter's blocks end anyway: checkpoints change no bit
            return n % CHUNK_ROWS == 0 or (self.state_path is not None and cal.boundary(n)
                                           and n // checkpoint_every > self.last_ck // checkpoint_every)

        self._cut = cut
        expect = (saved["input_bytes"], saved["input_sha256_prefix"]) if saved else None
        try:
            src = getattr(self, "_src", None) or CsvStream(
                self.data, cal.robot, cut=cut, measure=cal.method and cal.method.name, skip=skip, expect=expect,
                checked=self.ds_all is not None, throttle=throttle, column_map=cal.column_map)
        except (ValueError, OSError) as exc:
            self._fail(exc)
        self.src, self.shown = src, list(range(min(show, len(cal.names))))
        if self.state_path is not None and saved is None:
            self._save(src.position())  # the checkpoint is locked (and its place checked) before any row
        self._start_live(live)
        self._banner(skip, saved)
        n_total = self.ds_all.n if self.ds_all is not None else None
        del self.ds_all  # checked; the rows are streamed below
        quiet = live or n_total is None or self.every < 100
        bar = progress(total=n_total, desc="online", unit="row", enabled=False if quiet else None)
        bar.update(skip)
        try:
            with _Signals() as sig:
                for chunk in src:
                    with sig.busy():  # an update is never cut in the middle: its checkpoint stays exact
                        self._feed(chunk, bar)
        except CheckpointError as exc:
            self._fail(f"--resume {self.resume}: {exc} — resume needs the input the checkpointed run read (its "
                       f"first {saved['input_bytes']} bytes, {skip} data rows, unchanged)")
        except (ValueError, OSError) as exc:
            self._stop(exc)
        except KeyboardInterrupt:
            self._interrupted()
        finally:
            bar.close()
        if self.state_path is not None:
            self._save(self.src.position(), finished=True)
        if self.live_ctx is not None:
            self.live_ctx.stop()
        if cal.n_rows == 0:
            self._fail(f"{self.where}: no data rows")

    def _feed(self, chunk, bar):
        cal = self.cal
        if chunk.data is not None:
            try:
                up = cal.update(chunk.data, trace=self.trace is not None)
            except (ValueError, ArithmeticError) as exc:
                self._stop(exc)
            bar.update(up.n)
            if self.trace is not None:
                self.trace[0].extend(up.estimate)
                self.trace[1].extend(up.std)
            self._status(up)
            n = cal.n_rows
            if self.state_path is not None and n // self.every_ck > self.last_ck // self.every_ck:
                self._save(self.src.position())
                self.last_ck = n
        if chunk.error is not None:
            self._stop(chunk.error)

    def _stop(self, exc):
        """A bad row: keep what was computed before it."""
        from estcal.cli.common import message

        if self.state_path is not None:
            self._save(self.src.position())
        self._fail(message(exc))

    def _fail(self, msg):
        from rich.markup import escape

        if self.live_ctx is not None:  # leave the terminal clean before the message
            self.live_ctx.stop()
        self.err.print("[red]error:[/red] " + escape(str(msg)), soft_wrap=True)
        raise typer.Exit(2)

    def _interrupted(self):
        if self.state_path is not None:
            self._save(self.src.position())
        if self.live_ctx is not None:
            self.live_ctx.stop()
        if self.state_path is not None:
            self.err.print(f"interrupted after row {self.cal.n_rows} (line {self.src.last_line}); checkpoint "
                           f"{self.state_path} — continue with --resume {self.state_path}")
        raise typer.Exit(130)

    # ---------------------------------------------------------------- printing
    def _banner(self, skip, saved):
        from estcal.base.units import MILLI

        cal, o = self.cal, self.cal.options
        qp = o["--q-params"]
        q = o["q (SI)"]
        qs = f"{q / MILLI:g}" if isinstance(q, float) else str(q)
        self.console.print(f"estcal online: {cal.robot.name}, {len(cal.names)} free parameters, filter "
                           f"{cal.flt.kind}, q = {qs} mm / mrad{' on ' + qp if qp else ''}; reading {self.where}"
                           + (f"; resuming after row {skip} (line {saved['line']}) of {self.resume}" if saved else ""))

    def _start_live(self, live):
        from rich.live import Live

        from estcal.base.units import display_unit

        self.units = [display_unit(n, self.cal.robot) for n in self.cal.names]
        if live:
            self.live_ctx = Live("waiting for rows", console=self.console, refresh_per_second=4)
            self.live_ctx.start()

    def _status(self, up):
        cal, units = self.cal, self.units
        for h in up.history:
            if self.live_ctx is not None:
                self.live_ctx.update(self._live_table())
                continue
            x, s = h["estimate"], h["std"]
            par = "  ".join(f"{cal.names[i]}={x[i] * units[i][1]:.6g}±{s[i] * units[i][1]:.2g}"
                            f"{(' ' + units[i][0]) if units[i][0] else ''}" for i in self.shown)
            avg = h["nis_per_row"]  # undefined until the burn-in is over
            avg = f"{avg:.3f}" if avg == avg else "— (burn-in)"
            dim = int(up.dims[h["row"] - up.rows[0]])
            line = f"row {h['row']:5d}  NIS {h['nis']:7.2f}/{dim}  NIS/row(avg) {avg}  {par}"
            if self.console.is_terminal:
                self.console.print(line, soft_wrap=True)
            else:  # a pipe or a file: plain lines (rich's rendering costs ~0.3 ms a line: 10⁵ lines at 10⁶ rows)
                self.console.file.write(line + "\n")

    def _live_table(self):
        import numpy as np

        from estcal.base.tables import Table
        from estcal.report.tables import rich_table

        cal = self.cal
        pv = cal.robot.params
        x, sd = cal.estimate, cal.std
        rows = [[n, float(x[i] * f), float(sd[i] * f), float((x[i] - pv.values[cal.fidx[i]]) * f), u]
                for i, (n, (u, f)) in enumerate(zip(cal.names, self.units))]
        tb = Table("live", f"{cal.robot.name}: {cal.n_rows} rows, NIS/row {cal.running_nis:.3f}, trace P "
                           f"{np.trace(cal.flt.f.P):.3g}", ["parameter", "estimate", "std", "Δ from nominal", "unit"],
                   rows, fmt=lambda i, j, v, digits: f"{v:.{digits}g}" if j == 1 else f"{v:.3g}")
        return rich_table(tb, digits=6)

    def finish(self, json_path, report):
        from estcal.report.tables import rich_table

        res = self.cal.result()
        res.input = self.where
        table = res.table()  # the parameter table of the result (estcal.base.tables), its note the innovation tests
        self.console.print(rich_table(table, digits=6))
        self.console.print(table.note)
        tests = res.innovation
        out = res.to_dict()
        if json_path is not None:
            from estcal.base.jsonio import write_json

            write_json(json_path, out)
            self.console.print(f"JSON -> {json_path}")
        if report is not None:
            from estcal.report.online import online_report
            from estcal.base.units import display_unit

            mon = self.cal.flt.monitor
            online_report(report, res.names, res.nominal, self.trace[0].values, self.trace[1].values, mon.nis,
                          mon.dims, tests, unit=lambda n: display_unit(n, self.cal.robot),
                          title=f"estcal online — {res.robot}, {self.where}", result_dict=out)
            self.console.print(f"report -> {report}/index.html")
