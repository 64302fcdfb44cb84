"""The run report: one HTML page in the run folder, ``report.html``, that opens offline.

It shows what the folder holds: the configuration (config.json), the per-condition table
(summary.json, or the checkpoints' entries of an interrupted run), the rollouts on the arm by
kind with those stopped at a limit and a real arm's seconds (summary.json, eval.json), the Fig. 4 evaluation
(fig4.png, from scripts/evaluate.py), the retention curve (retention.png and the positions
forgotten, from scripts/retention.py) and every video in ``videos/`` (scripts/render.py).
Files are linked by paths relative to the folder, so the folder can be moved or shared; a part
whose file is missing is named with the command that makes it, and nothing absent is linked.
"""

from __future__ import annotations

import html
import json
from collections.abc import Iterable
from pathlib import Path
from typing import Any
from urllib.parse import quote

from lolgps_torch.data.run_folder import RunFolder, atomic_write, flatten, read_json
from lolgps_torch.evaluation.retention import forgotten

REPORT_FILE = "report.html"
RETENTION_FIGURE = "retention.png"
RETENTION_FILE = "retention.json"
VIDEO_DIR = "videos"
VIDEO_SUFFIXES = (".mp4", ".gif")

_STYLE = """
body { font-family: sans-serif; margin: 2em auto; max-width: 1100px; color: #222; }
table { border-collapse: collapse; font-size: 90%; margin: 0.5em 0 1.5em; }
th, td { border: 1px solid #ccc; padding: 2px 8px; text-align: right; }
th { background: #eee; } td.key { text-align: left; font-family: monospace; }
.miss { color: #b22; font-weight: bold; } .ok { color: #283; }
img, video { max-width: 100%; border: 1px solid #ccc; }
code { background: #f3f3f3; padding: 0 3px; }
"""


def _mm(value: Any) -> str:
    """A distance in m as mm with one decimal ('' for None, 'nan' kept)."""
    return "" if value is None else f"{1000 * float(value):.1f}"


def _table(header: Iterable[str], rows: Iterable[Iterable[Any]], key_column: bool = False) -> str:
    head = "".join(f"<th>{html.escape(str(h))}</th>" for h in header)
    body = []
    for row in rows:
        cells = []
        for i, cell in enumerate(row):
            css = ' class="key"' if key_column and i == 0 else ""
            cells.append(f"<td{css}>{cell}</td>")
        body.append(f"<tr>{''.join(cells)}</tr>")
    return f"<table><tr>{head}</tr>{''.join(body)}</table>"


def _outcome(success: Any) -> str:
    if success is None:
        return ""
    return '<span class="ok">success</span>' if success else '<span class="miss">miss</span>'


def condition_entries(folder: RunFolder, n_conditions: int) -> list[dict[str, Any]]:
    """summary.json's entries, or (an interrupted run) those of the checkpoints written so far."""
    if folder.summary_path.is_file():
        return list(folder.read_summary()["conditions"])
    return [folder.read_entry(c) for c in range(n_conditions) if folder.entry_path(c).is_file()]


def stage_names(stages: list[dict[str, Any]], n_conditions: int) -> list[str]:
    """The training stage of each condition: the first whose ``last_condition`` reaches it."""
    names = []
    for c in range(n_conditions):
        names.append(next((s["name"] for s in stages if c <= s["last_condition"]), ""))
    return names


def _configuration(config: dict[str, Any]) -> str:
    """The arm, method, seed and stages, then every setting (flattened) in a fold."""
    shown = {k: v for k, v in config.items() if k not in ("conditions", "stages")}
    settings = sorted(flatten(shown).items())
    rows = [(html.escape(key), html.escape(json.dumps(value))) for key, value in settings]
    stages = ", ".join(
        f"{html.escape(s['name'])} (to condition {int(s['last_condition'])})"
        for s in config.get("stages", [])
    )
    arm = html.escape(str(config.get("task", {}).get("urdf", "")))
    return (
        f"<p>Arm <code>{arm}</code>, method {html.escape(str(config.get('method', '')))}, "
        f"seed {html.escape(str(config.get('seed', '')))}; training stages: {stages}.</p>"
        f"<details><summary>All {len(rows)} settings (config.json)</summary>"
        f"{_table(('setting', 'value'), rows, True)}</details>"
    )


def _conditions(config: dict[str, Any], entries: list[dict[str, Any]]) -> str:
    offsets = config.get("conditions", [])
    stages = stage_names(config.get("stages", []), len(offsets))
    rows = []
    for e in entries:
        c = int(e["condition"])
        dx, dy = (1000 * float(v) for v in e["offset"])
        rows.append(
            (
                c,
                html.escape(stages[c] if c < len(stages) else ""),
                f"{dx:+.1f}, {dy:+.1f}",
                e.get("iterations", ""),
                e.get("rollouts", ""),
                " / ".join(str(n) for n in e.get("arm_rollouts", {}).values()),
                sum(e["arm_faults"].values()) if "arm_faults" in e else "",
                "" if e.get("first_success_iteration") is None else e["first_success_iteration"],
                _mm(e.get("local_final_distance")),
                _mm(e.get("policy_final_distance_after")),
                _mm(e.get("policy_final_distance_end")),
                _outcome(e.get("policy_success_end", e.get("policy_success_after"))),
                e.get("repairs", ""),
                html.escape(str(e.get("failure") or "")),
            )
        )
    header = (
        "condition", "stage", "hole offset (mm)", "iterations", "rollouts",
        "on the arm: samples / probes / visits", "stopped at a limit", "first success", "p_cur (mm)", "policy after (mm)", "policy end (mm)", "policy",
        "repairs", "failure",
    )  # fmt: skip
    done = f"{len(entries)} of {len(offsets)} conditions completed"
    if entries and "policy_final_distance_end" not in entries[0]:
        done += " (interrupted run: no final policy test yet)"
    return (
        f"<p>{done}. Distances are noiseless final tip distances to the hole's floor; "
        "'after' right after the condition's own S-step, 'end' the final policy's.</p>"
        + _table(header, rows)
    )


def _arm_use(folder: RunFolder) -> str:
    """The rollouts on the arm by kind (summary.json's, with eval.json's evaluation), those
    stopped at a limit and a real arm's seconds."""
    summary = folder.read_summary() if folder.summary_path.is_file() else {}
    counted = dict(summary.get("arm_rollouts", {}))
    if folder.eval_path.is_file():
        counted |= read_json(folder.eval_path).get("arm_rollouts", {})
    if not counted:
        return "<p>Not counted: the stream has not finished, or predates the count.</p>"
    total = counted.pop("total", None)
    kinds = ", ".join(f"{n} {html.escape(kind)}" for kind, n in counted.items())
    stream = f" ({total} while learning)" if total is not None else ""
    text = f"<p>Rollouts on the arm: {kinds}{stream}."
    faults = dict(summary.get("arm_faults", {}))
    if faults:
        stopped = ", ".join(f"{n} {html.escape(k)}" for k, n in faults.items() if k != "total")
        text += f" Stopped at a limit while learning: {faults.get('total', 0)} ({stopped})."
    if summary.get("model_rollouts"):
        text += (
            f" Rollouts on the arm's model instead (visits): {summary['model_rollouts']}"
            f" ({summary.get('model_faults', 0)} stopped at a limit)."
        )
    if "arm_seconds" in summary:
        text += f" Seconds on the arm while learning: {float(summary['arm_seconds']):.0f}."
    return text + "</p>"


def _figure(folder: Path, name: str, alt: str, command: str) -> str:
    if (folder / name).is_file():
        return f'<p><img src="{html.escape(quote(name))}" alt="{html.escape(alt)}"></p>'
    return f"<p>Not made yet: <code>{html.escape(command)}</code>.</p>"


def _retention(folder: Path) -> str:
    part = _figure(
        folder, RETENTION_FIGURE, "retention curve", "python scripts/retention.py --run DIR"
    )
    path = folder / RETENTION_FILE
    if path.is_file():
        lost = forgotten(read_json(path)) or "none"
        part += f"<p>Forgotten (succeeded after their own S-step, missed at the end): {lost}.</p>"
    return part


def videos(folder: Path) -> list[str]:
    """The videos in the run folder's ``videos/``, as paths relative to the folder."""
    directory = folder / VIDEO_DIR
    if not directory.is_dir():
        return []
    return sorted(
        f"{VIDEO_DIR}/{p.name}"
        for p in directory.iterdir()
        if p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES
    )


def _videos(folder: Path) -> str:
    found = videos(folder)
    if not found:
        return "<p>Not made yet: <code>python scripts/render.py --run DIR</code>.</p>"
    parts = []
    for name in found:
        src = html.escape(quote(name))
        if name.lower().endswith(".gif"):
            media = f'<img src="{src}" alt="{src}">'
        else:
            media = f'<video src="{src}" controls loop muted playsinline></video>'
        parts.append(f"<h3><code>{html.escape(name)}</code></h3><p>{media}</p>")
    return "".join(parts)


def report_html(path: str | Path) -> str:
    """The report of the run folder at ``path`` (module docstring), as HTML text."""
    folder = RunFolder(path)
    config = folder.read_config()
    entries = condition_entries(folder, len(config.get("conditions", [])))
    title = f"{folder.path.resolve().name}: {config.get('method', '')} run, seed {config.get('seed', '')}"
    sections = [
        ("Configuration", _configuration(config)),
        ("Conditions", _conditions(config, entries)),
        ("Time on the arm", _arm_use(folder)),
        ("Evaluation (Fig. 4)", _figure(folder.path, folder.figure_path.name, "Fig. 4", "python scripts/evaluate.py --run DIR")),
        ("Retention", _retention(folder.path)),
        ("Videos", _videos(folder.path)),
    ]  # fmt: skip
    body = "".join(f"<h2>{html.escape(h)}</h2>{part}" for h, part in sections)
    return (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        f"<title>{html.escape(title)}</title><style>{_STYLE}</style></head>"
        f"<body><h1>{html.escape(title)}</h1>{body}</body></html>\n"
    )


def write_report(path: str | Path) -> Path:
    """Write :func:`report_html` to ``report.html`` in the run folder, atomically."""
    text = report_html(path)
    out = Path(path) / REPORT_FILE
    atomic_write(out, lambda tmp: tmp.write_text(text))
    return out
