"""TIAGo at new postures of another session: the default ``estcal diagnose`` on a posture- and session-disjoint
protocol, fixed before the model was scored (docs/discrepancy.md, "How accurate, on the real robots").

Protocol (``../shared/data/tiago``, never copied):

* both sessions, 11-30 (37 rows) and 11-26 (62 rows); a posture is every row whose joint readings agree within
  1e-3 rad / 1e-3 m, over both sessions: 62 postures;
* a halving with seed ``s``: ``numpy.random.default_rng(s).permutation(postures)[: 62 // 2]`` is half A;
* direction 1: train on 11-30's rows at half A; the validation file is all of 11-26 — its rows at half A
  register its measuring frame (the diagnosis does it: docs/discrepancy.md) and, since the sixth confirmation
  set was declared, any joint zero those rows alone show moved since training (``estcal.discrepancy.zeros``;
  before, the frame only), its rows at half B are the score. Direction 2: the sessions swapped;
* every row carries the approach directions of its own session's acquisition (the side each joint moved from
  into the posture, from the whole session's time order — what ``estcal diagnose`` derives from a whole file);
* development seeds 0–5 (the model was developed on them); confirmation seeds 20, 21, 22, fixed before any of
  them was scored; a second confirmation set 40, 41, 42, declared before it was scored when 20–22 had been run
  with two versions of the model (``--seeds confirmation2``); a third, 60, 61, 62, declared before the last
  version's changes and run once with it (``--seeds confirmation3``); a fourth, 80, 81, 82, declared before
  backlash by approach became a default candidate, run once with it (``--seeds confirmation4``); a fifth,
  100, 101, 102, declared before a further candidate was tried and rejected on them (``--seeds confirmation5``);
  a sixth, 120, 121, 122, declared before the moved joint zeros were registered, run once with it
  (``--seeds confirmation6``); a seventh, 140, 141, 142, and an eighth, 160, 161, 162, declared before the
  link frames' priors were bounded (``--geometric-width-mm 1``, an option, not the default), each run once with
  the bound (``--seeds confirmation7`` / ``confirmation8``) and with the default; a ninth, 180, 181, 182,
  declared before a cross-validated choice of that bound was tried, run once with it (it chose the default
  everywhere; not adopted) and then with the default and the bound (``--seeds confirmation9``); a tenth,
  200, 201, 202, declared before the link frames' width was chosen by the one-standard-error rule (the
  default since), run once with it (``--seeds confirmation10``; the former, unbounded default run on it too);
  an eleventh, 220, 221, 222, declared before the named special terms were tested against the load terms the
  evidence keeps (the default since), run once with and without that test (``--seeds confirmation11``).
  ``--seeds all`` runs the 72 halvings of the development and first ten confirmation sets (the studies' common
  ground, measured before the eleventh was run).

Per halving: the RMSE at the new postures (the diagnosis's own validation figure), the prediction (the
budget's expected error, and the prediction at the validation file's postures), their ratio, the 95 % region's
coverage, the named causes, the joint zeros that moved between the sessions, the CPU time. ``--json PATH`` writes
everything.
"""
from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from estcal.base.jsonio import write_json  # noqa: E402
from estcal.kinematics.robots import shared_dir  # noqa: E402

DEVELOPMENT = (0, 1, 2, 3, 4, 5)
CONFIRMATION = (20, 21, 22)
#: declared before they were scored, to confirm a change after 20–22 had been run twice
CONFIRMATION2 = (40, 41, 42)
#: declared before the backward naming step was written, run once with it
CONFIRMATION3 = (60, 61, 62)
#: declared before backlash by approach (directions from the acquisition order) became a default candidate
CONFIRMATION4 = (80, 81, 82)
#: declared before a load-proportional lag was tried as a further candidate (rejected on them)
CONFIRMATION5 = (100, 101, 102)
#: declared before a validation file's moved joint zeros were registered on its seen rows
CONFIRMATION6 = (120, 121, 122)
#: declared before the link frames' priors were bounded at 1 mm / 1 mrad (``--geometric-width-mm 1``)
CONFIRMATION7 = (140, 141, 142)
#: declared before that bound's second confirmation
CONFIRMATION8 = (160, 161, 162)
#: declared before the bound was chosen by cross-validation (tried, not adopted)
CONFIRMATION9 = (180, 181, 182)
#: declared before the link frames' width was chosen by the one-standard-error rule (``geometric_width="auto"``)
CONFIRMATION10 = (200, 201, 202)
#: declared after the tenth for the next candidate; run once with the test of named special terms against the
#: load terms (adopted) and without it. Not in ``all``: the studies' 72 halvings were measured before it
CONFIRMATION11 = (220, 221, 222)
#: declared after the eleventh for the next change; run once with every penalised column in the span of earlier
#: ones kept out of the evidence search (a version never adopted: in small folds it dropped every late column),
#: then with the adopted one (only columns that repeat an earlier one: ``experiments/rounding.py``). Not in ``all``
CONFIRMATION12 = (240, 241, 242)
#: declared before the adopted version was scored anywhere but the development halvings; run once with it
CONFIRMATION13 = (260, 261, 262)
#: declared before a range-blocked test of named harmonics and encoder gains was scored; run once with it (it
#: changed nothing on these halvings), then with the default (the same figures); the test was not adopted
CONFIRMATION14 = (280, 281, 282)
#: declared before a gear harmonic of order n became a candidate only over half its period (the default since);
#: run once with it
CONFIRMATION15 = (300, 301, 302)
FILES = {"11-30": "qualisys_2021-11-30_static_postures.csv", "11-26": "qualisys_2021-11-26_static_postures.csv"}


def missing() -> str | None:
    """Why the study cannot run here (the shared TIAGo data are absent), else None."""
    return None if (shared_dir() / "data" / "tiago").is_dir() else f"shared data not found at {shared_dir() / 'data'}"


def load():
    """The TIAGo robot (the built-in ``tiago``, URDF masses as ``estcal diagnose`` loads them) and both sessions,
    each row with the approach directions of its session's acquisition (``approach_<joint>``, from the whole
    session's time order, as ``estcal diagnose`` derives them from a whole file): a half keeps the moves the robot
    made, not moves between postures it never went between."""
    from estcal.discrepancy.masses import with_urdf_masses
    from estcal.io import load_dataset
    from estcal.io.prepare import derive_approach
    from estcal.kinematics import tiago

    robot = with_urdf_masses(tiago(n_markers=4))
    folder = shared_dir() / "data" / "tiago"
    return robot, {k: derive_approach(load_dataset(folder / f, robot)) for k, f in FILES.items()}


def halvings(robot, sessions, seeds):
    """``[(seed, train session, training rows (Dataset), validation Dataset)]`` of the protocol."""
    from estcal.validation import posture_groups

    a, b = sessions["11-30"], sessions["11-26"]
    g = posture_groups(np.vstack([a.readings, b.readings]), robot.joint_types)
    lab = {"11-30": g[: a.n], "11-26": g[a.n:]}
    out = []
    for s in seeds:
        half = np.random.default_rng(s).permutation(np.unique(g))[: len(np.unique(g)) // 2]
        for tr, va in (("11-30", "11-26"), ("11-26", "11-30")):
            out.append((s, tr, sessions[tr].subset(np.flatnonzero(np.isin(lab[tr], half))), sessions[va]))
    return out


def _zeros_text(zeros) -> str:
    return ", ".join(f"{j} {1e3 * x:+.1f} ± {1e3 * e:.1f}" for j, (x, e) in zeros.items()) or "none"


def width_text(choice, width) -> str:
    """The link frames' prior width of one halving's model, for the log line (``talos_split.py`` prints it too):
    the one-standard-error rule's choice and the CV errors it compared, or the width that was given."""
    if choice:
        return (f"{'bounded' if choice['bounded'] else 'unbounded'} (CV {choice['cv_bounded_mm']:.2f} bounded, "
                f"{choice['cv_unbounded_mm']:.2f} + 1 SE {choice['cv_unbounded_plus_se_mm']:.2f} unbounded)")
    if isinstance(width, str):  # auto with no choice made: no link frame under a prior
        return "not bounded (no link frame under a prior)"
    return "unbounded" if width is None else f"within {width * 1e3:g} mm / mrad"


def run(seeds, folds=5, register_zeros=True, geometric_width="auto"):
    from estcal.workflows.diagnose import diagnose

    robot, sessions = load()
    rows = []
    for s, tr, T, V in halvings(robot, sessions, seeds):
        t0 = time.process_time()
        res = diagnose(robot, T, validate=[V], folds=folds, register_zeros=register_zeros,
                       geometric_width=geometric_width)
        cpu = time.process_time() - t0
        v = res.accuracy["validation"][0]
        r = {"seed": s, "train": tr, "n_train": T.n, "new_mm": v["rmse_mm"], "new_se_mm": v["rmse_se_mm"],
             "n_new": v["n_new"],
             "registered_on": v["n_seen"], "expected_mm": res.answer["expected_mm"],
             "predicted_at_mm": v["predicted_mm"], "coverage": v["coverage"],
             "ratio_expected": res.answer["expected_mm"] / v["rmse_mm"],
             "ratio_at": (v["predicted_mm"] or np.nan) / v["rmse_mm"],
             "named": [c.label for c in res.causes], "cpu_s": cpu,
             "width_choice": res.model.get("geometric_width_choice"),
             "zeros_moved": {z["joint"]: [z["value"], z["std"]] for z in v.get("zeros_moved", [])}}
        rows.append(r)
        print(f"seed {s:2d} train {tr} ({T.n:2d} rows): new postures {r['new_mm']:.2f} ± {r['new_se_mm']:.2f} mm "
              f"({r['n_new']} rows); "
              f"expected {r['expected_mm']:.2f} (ratio {r['ratio_expected']:.2f}), at its postures "
              f"{r['predicted_at_mm']:.2f} (ratio {r['ratio_at']:.2f}); coverage {r['coverage']:.2f}; "
              f"named {r['named']}; zeros moved {_zeros_text(r['zeros_moved'])}; link frames "
              f"{width_text(r['width_choice'], geometric_width)}; {cpu:.1f} s CPU", flush=True)
    new = np.array([r["new_mm"] for r in rows])
    print(f"mean at new postures {new.mean():.2f} mm (median {np.median(new):.2f}); within 30 %: expected "
          f"{sum(0.7 <= r['ratio_expected'] <= 1.3 for r in rows)}/{len(rows)}, at its postures "
          f"{sum(0.7 <= r['ratio_at'] <= 1.3 for r in rows)}/{len(rows)}")
    attainable = attainable_within(rows)
    print(f"a prediction equal to each halving's expected RMSE would be within 30 % on about {attainable:.1f} of "
          f"{len(rows)} (the validation figure's own sampling error over its postures)")
    named = named_counts(rows)
    print(f"named in how many of the {len(rows)} halvings: "
          + "; ".join(f"{c} {n}" for c, n in named["causes"].items())
          + f"; the most common list ({named['most_common_list_count']}): "
          + (", ".join(named["most_common_list"]) or "nothing named"))
    return {"rows": rows, "mean_new_mm": float(new.mean()), "attainable_within_30": attainable, "named": named}


def named_counts(rows) -> dict:
    """How often each cause is named over the halvings (most often first), and the most common whole list."""
    from collections import Counter

    causes = Counter(c for r in rows for c in set(r["named"]))
    lists = Counter(tuple(sorted(set(r["named"]))) for r in rows)
    top, k = lists.most_common(1)[0]
    return {"causes": dict(causes.most_common()), "most_common_list": list(top), "most_common_list_count": k}


def attainable_within(rows, tol: float = 0.3) -> float:
    """How many halvings a perfect prediction would get within ``tol``: the validation RMSE ``A`` of a halving
    scatters about its expectation ``μ`` with the standard error over its postures (``new_se_mm``,
    :func:`estcal.validation.rmse_se_mm`); a prediction equal to ``μ`` is within ``tol`` when ``μ/(1+tol) ≤ A ≤
    μ/(1−tol)``, with probability ``Φ((μ/(1−tol) − μ)/se) − Φ((μ/(1+tol) − μ)/se)`` (normal, ``μ`` plugged in
    as the observed RMSE). The sum over halvings — a ceiling for the "within 30 % on each halving" count, from
    the postures' sampling alone (a session's own shift adds to it)."""
    from scipy.stats import norm

    out = 0.0
    for r in rows:
        mu, se = r["new_mm"], r.get("new_se_mm")
        if not se:
            out += 1.0
            continue
        out += float(norm.cdf((mu / (1 - tol) - mu) / se) - norm.cdf((mu / (1 + tol) - mu) / se))
    return out


#: the declared seed sets by name (the module docstring says when each was declared and what it decided)
SEED_SETS = {"development": DEVELOPMENT, "confirmation": CONFIRMATION, "confirmation2": CONFIRMATION2,
             "confirmation3": CONFIRMATION3, "confirmation4": CONFIRMATION4, "confirmation5": CONFIRMATION5,
             "confirmation6": CONFIRMATION6, "confirmation7": CONFIRMATION7, "confirmation8": CONFIRMATION8,
             "confirmation9": CONFIRMATION9, "confirmation10": CONFIRMATION10, "confirmation11": CONFIRMATION11,
             "confirmation12": CONFIRMATION12, "confirmation13": CONFIRMATION13,
             "confirmation14": CONFIRMATION14, "confirmation15": CONFIRMATION15}
#: the sets declared from the eleventh on, each run once with the version it was declared for; ``--seeds all``
#: runs every other set (module docstring)
LATER = ("confirmation11", "confirmation12", "confirmation13", "confirmation14", "confirmation15")
ALL = tuple(k for k in SEED_SETS if k not in LATER)


def seed_set(text: str) -> tuple:
    """Seeds from ``--seeds``: a set's name, ``all`` (the sets of :data:`ALL`, in order), or a comma-separated list."""
    if text == "all":
        return tuple(s for k in ALL for s in SEED_SETS[k])
    try:
        return SEED_SETS.get(text) or tuple(int(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is neither a seed set ({', '.join(SEED_SETS)}, all) nor a "
                                         "comma-separated list of integers") from None


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=seed_set, default="development", help="development (0–5), confirmation "
                    "(20–22), confirmation2 (40–42), confirmation3 (60–62), confirmation4 (80–82), confirmation5 (100–102), confirmation6 "
                    "(120–122), confirmation7 (140–142), confirmation8 (160–162), confirmation9 (180–182), "
                    "confirmation10 (200–202), confirmation11 (220–222), confirmation12 (240–242), confirmation13 "
                    "(260–262), confirmation14 (280–282), confirmation15 (300–302), all (the 72 halvings of the sets "
                    "declared before the eleventh) or a list")
    ap.add_argument("--folds", type=int, default=5)
    ap.add_argument("--frame-only", action="store_true", help="register the validation file's measuring frame only "
                    "(the protocol before the sixth confirmation set: no moved joint zero)")
    ap.add_argument("--geometric-width-mm", default="auto", help="the link frames' priors (`estcal diagnose "
                    "--geometric-width-mm`): auto (the diagnosis's default: 1 mm / 1 mrad unless the unbounded model's "
                    "CV error is lower by more than one standard error), inf (unbounded) or a bound in mm and mrad")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    warnings.filterwarnings("ignore")
    if missing():
        print(missing())
        return {"skipped": True}
    seeds = args.seeds
    from estcal.workflows.diagnose import width_from_text

    width = width_from_text(args.geometric_width_mm)
    out = {"protocol": __doc__, "seeds": list(seeds), "frame_only": args.frame_only,
           "geometric_width_mm": args.geometric_width_mm, **run(seeds, args.folds, not args.frame_only, width)}
    if args.json:
        write_json(args.json, out, announce=True)
    return out


if __name__ == "__main__":
    main()
