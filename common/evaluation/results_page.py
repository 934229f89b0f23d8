"""``needletrack results``: every figure of ``docs/results.md`` from one source, the
``results.json`` that ``needletrack eval`` writes.

``docs/results/sets.yaml`` lists the sets: a name, a title, its family (``in-look``: looks the
detector was trained on; ``held-out``: a look family kept out of training and of every fit), the
command that makes it (``needletrack dataset ...`` with ``{dir}`` for its folder and ``{data}``
for the folder of all sets, so a set may be made from one listed before it) and the
``eval`` options. ``needletrack results run --data DIR`` makes each missing set under DIR,
evaluates it and keeps its summary as ``docs/results/NAME.json`` (the results without per-node
counters and overlay names: a few kB). ``needletrack results page`` writes ``docs/results.md``
from the summaries alone, so the page and the figures cannot disagree; a test regenerates it.
"""
from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path

import yaml

from common.errors import NeedletrackError
from common.methods import BY_NAME, FINAL_ORDER

REPO = Path(__file__).resolve().parents[2]
SETS = REPO / "docs" / "results" / "sets.yaml"
PAGE = REPO / "docs" / "results.md"
DROPPED = ("node_counters", "overlays", "dataset")
"""Left out of a kept summary: per-node counters and overlay names (per run), the folder's path
(the machine's own; the set's name and command say what it was)."""


class ResultsError(NeedletrackError, ValueError):
    """A sets file or a summary that cannot be used; the message names the file and the field."""


def load_sets(path: Path = SETS) -> list[dict]:
    """The sets of ``path``, each with ``name``, ``title``, ``family``, ``make``, ``eval``."""
    try:
        doc = yaml.safe_load(Path(path).read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise ResultsError(f"{path}: cannot read: {exc}") from None
    sets = doc.get("sets") if isinstance(doc, dict) else None
    if not isinstance(sets, list) or not sets:
        raise ResultsError(f"{path}: expected a non-empty list 'sets'")
    seen = set()
    for i, s in enumerate(sets):
        where = f"{path}: sets[{i}]"
        if not isinstance(s, dict):
            raise ResultsError(f"{where}: expected a mapping")
        for key in ("name", "title", "family", "make", "eval"):
            if not isinstance(s.get(key), str):
                raise ResultsError(f"{where}.{key}: expected a string")
        if s["family"] not in ("in-look", "held-out"):
            raise ResultsError(f"{where}.family: expected in-look or held-out, got {s['family']!r}")
        if "{dir}" not in s["make"]:
            raise ResultsError(f"{where}.make: the command must write to {{dir}}")
        if s["name"] in seen:
            raise ResultsError(f"{where}.name: {s['name']!r} twice")
        seen.add(s["name"])
    return sets


def summary(results: dict, set_name: str) -> dict:
    """What is kept of a ``results.json``: all but ``DROPPED``, with the set's name."""
    out = {k: v for k, v in results.items() if k not in DROPPED}
    out["set"] = set_name
    return out


# ---------------------------------------------------------------- the page

def _f(x, fmt: str = ".2f") -> str:
    return "-" if x is None else format(x, fmt)


def _pct(x) -> str:
    return "-" if x is None else f"{100 * x:.1f}%"


def _mm_deg(p: dict, stat: str) -> str:
    return f"{_f(p['position_mm'][stat])} / {_f(p['orientation_deg'][stat])}"


def method_table(r: dict) -> list[str]:
    """The methods on one set against the paper (Table III), in the registry's final order."""
    kp = r["keypoints_2d_px"]["all"]
    paper_kp = r.get("paper", {}).get("keypoints_2d_px", {}).get("all")
    rows = ["| method | mm / deg, mean (median) | posed | paper: mean |", "| --- | --- | --- | --- |",
            f"| keypoint detector, 2D error | {_f(kp['mean'])} px ({_f(kp['median'])}) | "
            f"{_pct(r['detection_rate'])} of {r['images']} images found | {_f(paper_kp)} px |"]
    for m in FINAL_ORDER:
        p = r["pose"].get(m)
        if p is None:
            continue
        paper = BY_NAME[m].paper
        unit = "sequences" if BY_NAME[m].multiview else "frames"
        rows.append(f"| `{m}` ({BY_NAME[m].label}) | {_mm_deg(p, 'mean')} ({_mm_deg(p, 'median')}) | {p['n']} / {p['expected']} "
                    f"{unit} | {'-' if paper is None else f'{paper[0]:.2f} / {paper[1]:.2f}'} |")
    return rows


def looks_table(sets: list[dict], results: dict) -> list[str]:
    """``refined`` on every set: found, keypoints, accuracy, posed, turned, NEES, unflagged."""
    rows = ["| set | family | found | keypoints px | `refined` mm / deg, mean (median) | modulo the turn | posed | "
            "turned | confident swaps | undecided | tip stated / measured turned | calibrated bins "
            "| NEES median | sure and right | not flagged: n, mm / deg |",
            "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for s in sets:
        r = results.get(s["name"])
        if r is None:
            rows.append(f"| {s['title']} | {s['family']} | not measured yet |" + " |" * 12)
            continue
        p = r["pose"].get("refined")
        kp = r["keypoints_2d_px"]["all"]
        if p is None:
            rows.append(f"| {s['title']} | {s['family']} | {_pct(r['detection_rate'])} | {_f(kp['mean'])} | "
                        "no `refined` |" + " |" * 10)
            continue
        e = p.get("end_for_end", {})
        ei = p.get("end_identity", {}).get("all", {})
        sure = p.get("sure")
        sure_s = "-" if not sure else f"{sure['n']}, {_mm_deg(sure, 'mean')}"
        mt = p.get("modulo_turn")
        rel = p.get("reliability")
        cal = "-" if not rel else f"{sum(b['within_bound'] for b in rel)} of {len(rel)}"
        und = p.get("undecided")
        rows.append(f"| {s['title']} | {s['family']} | {_pct(r['detection_rate'])} | {_f(kp['mean'])} | "
                    f"{_mm_deg(p, 'mean')} ({_mm_deg(p, 'median')}) | "
                    f"{'-' if not mt else _mm_deg(mt, 'mean')} | {p['n']} / {p['expected']} | "
                    f"{_pct(e.get('share'))} | {p.get('confident_swaps', '-')} | "
                    f"{'-' if not und else _pct(und['share'])} | "
                    f"{_pct(ei.get('stated'))} / {_pct(ei.get('measured'))} | {cal} | "
                    f"{_f(p.get('nees', {}).get('median'), '.1f')} | {_pct(p.get('sure_and_right'))} | {sure_s} |")
    return rows


def page(sets: list[dict], results: dict) -> str:
    """docs/results.md from the sets and their summaries (``{name: summary}``)."""
    lines = ["# Results", "",
             "Generated by `needletrack results page` from `docs/results/*.json`, the summaries of",
             "`needletrack eval` on each set of [results/sets.yaml](results/sets.yaml); do not edit by hand.",
             "`needletrack results run --data DIR` remakes the sets and their figures on another machine.",
             "What the columns mean: [evaluation.md](evaluation.md).", ""]
    first = sets[0]
    if first["name"] in results:
        lines += [f"## {first['title']}", "", f"`needletrack eval --dataset DIR {first['eval']}`", ""]
        lines += method_table(results[first["name"]]) + [""]
    lines += ["## Across looks", "",
              "`refined` on every set. Turned: poses more than 150 deg off. Confident swaps: turned poses",
              "that state a sure tip (at least 0.95) or are not flagged. Undecided: poses flagged with an",
              "unsure tip; modulo the turn scores them against the nearer of their two readings. Tip",
              "stated / measured turned: the share of poses expected turned from their stated tip",
              "probability, and the share found turned; calibrated bins: bins of the stated probability",
              "whose measured turned share is at most 1.5 x the stated + 2 points. Sure and right: frames",
              "posed unflagged within 2 mm / 5 deg, of all frames. Held-out sets' looks were kept out of",
              "training and of every fit.", ""]
    lines += looks_table(sets, results) + ["", "## The sets", "",
                                          "| set | made by | evaluated with |", "| --- | --- | --- |"]
    for s in sets:
        lines.append(f"| {s['title']} | `needletrack {s['make'].format(dir='DIR', data='DATA')}` | "
                     f"`needletrack eval --dataset DIR {s['eval']}` |")
    return "\n".join(lines) + "\n"


def load_results(sets: list[dict], folder: Path) -> dict:
    """``{name: summary}`` of the sets whose ``folder/NAME.json`` exists."""
    out = {}
    for s in sets:
        f = Path(folder) / f"{s['name']}.json"
        if f.exists():
            try:
                out[s["name"]] = json.loads(f.read_text())
            except json.JSONDecodeError as exc:
                raise ResultsError(f"{f}: not JSON: {exc}") from None
    return out


# ---------------------------------------------------------------- the command

def run_set(s: dict, data: Path, out: Path, keep: Path, log=print) -> None:
    """Make set ``s`` under ``data`` if missing, evaluate it into ``out/NAME``, keep its summary."""
    from common.cli import main as needletrack
    folder = Path(data) / s["name"]
    if not (folder / "frames.jsonl").exists():
        log(f"results: making {s['name']}: needletrack {s['make'].format(dir=folder, data=data)}")
        if needletrack(shlex.split(s["make"].format(dir=shlex.quote(str(folder)), data=shlex.quote(str(data))))) != 0:
            raise ResultsError(f"results: making {s['name']} failed")
    log(f"results: evaluating {s['name']}")
    ev = Path(out) / s["name"]
    if needletrack(["eval", "--dataset", str(folder), "--out", str(ev), "--quiet", *shlex.split(s["eval"])]) != 0:
        raise ResultsError(f"results: evaluating {s['name']} failed (log: {ev / 'graph.log'})")
    res = json.loads((ev / "results.json").read_text())
    Path(keep).mkdir(parents=True, exist_ok=True)
    (Path(keep) / f"{s['name']}.json").write_text(json.dumps(summary(res, s["name"]), indent=1) + "\n")


def main(argv: list) -> int:
    ap = argparse.ArgumentParser(prog="needletrack results", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="what", required=True)
    r = sub.add_parser("run", help="make and evaluate the sets, keep their summaries, write the page")
    r.add_argument("--data", required=True, help="folder for the sets' datasets (made when missing)")
    r.add_argument("--out", default="results", help="folder for the full evaluations (default results/)")
    r.add_argument("--only", action="append", default=[], metavar="NAME", help="only this set (repeatable)")
    pg = sub.add_parser("page", help="write docs/results.md from the kept summaries")
    for p in (r, pg):
        p.add_argument("--sets", default=str(SETS), help="the sets file (default docs/results/sets.yaml)")
        p.add_argument("--page", default=str(PAGE), help="the page to write (default docs/results.md)")
    args = ap.parse_args(argv)
    try:
        sets = load_sets(Path(args.sets))
        keep = Path(args.sets).parent
        if args.what == "run":
            unknown = set(args.only) - {s["name"] for s in sets}
            if unknown:
                raise ResultsError(f"results: no set named {sorted(unknown)} in {args.sets}")
            for s in sets:
                if not args.only or s["name"] in args.only:
                    run_set(s, Path(args.data), Path(args.out), keep)
        text = page(sets, load_results(sets, keep))
    except ResultsError as exc:
        print(exc, file=sys.stderr)
        return 2
    Path(args.page).write_text(text)
    print(f"results: wrote {args.page}")
    return 0
