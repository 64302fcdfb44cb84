"""The run report: report.html links only files that exist in the run folder, by relative
paths, and shows the configuration, the per-condition table, the figures and the videos."""

from __future__ import annotations

import json
import runpy
import sys
from html.parser import HTMLParser
from pathlib import Path
from typing import Any
from urllib.parse import unquote

import pytest
from PIL import Image

from lolgps_torch.data.run_folder import RunFolder, portable_urdf, task_json
from lolgps_torch.evaluation.report import REPORT_FILE, report_html, write_report
from lolgps_torch.task import TaskConfig

ROOT = Path(__file__).resolve().parents[1]
KUKA = "robots/kuka_peg.urdf"
SCRIPT = ROOT / "scripts" / "report.py"
CONDITIONS = [[0.0, 0.0], [0.02, -0.01], [0.0, 0.05]]
STAGES = [{"name": "train0", "last_condition": 1}, {"name": "train1", "last_condition": 2}]


class Page(HTMLParser):
    """Every ``src``/``href`` of a page, the text of its table cells, and its open tags left."""

    def __init__(self, text: str) -> None:
        super().__init__()
        self.links: list[str] = []
        self.cells: list[list[str]] = []
        self.open: list[str] = []
        self._cell = False
        self.feed(text)

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        self.links += [v for k, v in attrs if k in ("src", "href") and v is not None]
        if tag == "tr":
            self.cells.append([])
        if tag == "td":
            self.cells[-1].append("")
            self._cell = True
        if tag not in ("img", "meta", "br"):
            self.open.append(tag)

    def handle_endtag(self, tag: str) -> None:
        assert self.open and self.open[-1] == tag, (self.open, tag)
        self.open.pop()
        self._cell = self._cell and tag != "td"

    def handle_data(self, data: str) -> None:
        if self._cell:
            self.cells[-1][-1] += data


def make_run(folder: Path, finished: bool = True) -> None:
    """config.json and the entries of a three-condition run (all of them finished, or the
    first two of an interrupted run), without any learning."""
    urdf_text = portable_urdf(KUKA)
    config = {
        "task": task_json(TaskConfig(urdf=KUKA), urdf_text),
        "conditions": CONDITIONS,
        "stages": STAGES,
        "method": "lolgps",
        "seed": 3,
        "stream": {"max_iterations": 25, "policy": {"steps": 3000}},
    }
    run = RunFolder(folder)
    run.start(config, urdf_text)
    entries: list[dict[str, Any]] = [
        {"condition": c, "offset": o, "iterations": 10 + c, "rollouts": 50, "first_success_iteration": 2,
         "local_final_distance": 0.0012, "policy_final_distance_after": 0.001 * (c + 1),
         "policy_success_after": True, "repairs": 0, "failure": None,
         "arm_rollouts": {"sample": 45, "probe": 3, "visit": 9 * (c + 1)},
         "arm_faults": {"sample": c, "probe": 0, "visit": 0}}
        for c, o in enumerate(CONDITIONS)
    ]  # fmt: skip
    for entry in entries[:2]:
        run.write_entry(entry["condition"], entry)
    if finished:
        for entry, end in zip(entries, (0.0011, 0.094, 0.0013), strict=True):
            entry.update(policy_final_distance_end=end, policy_success_end=end < 0.06)
        counted = {"start": 130, "sample": 135, "probe": 12, "visit": 54, "total": 331}
        faults = {"sample": 3, "probe": 0, "visit": 0, "total": 3}
        run.write_summary({"method": "lolgps", "seed": 3, "arm_rollouts": counted,
                           "arm_faults": faults, "conditions": entries})  # fmt: skip


def add_outputs(folder: Path) -> None:
    """fig4.png, the retention curve and table, and a video of each kind."""
    for name in ("fig4.png", "retention.png"):
        Image.new("RGB", (8, 8), (200, 30, 30)).save(folder / name)
    distance = [[0.001, 0.2, 0.3], [0.09, 0.001, 0.2], [0.09, 0.002, 0.001]]
    table = {"conditions": [0, 1, 2], "success_threshold": 0.06, "distance": distance}
    (folder / "retention.json").write_text(json.dumps(table))
    (folder / "videos").mkdir()
    (folder / "videos" / "policy-wide.mp4").write_bytes(b"\0" * 16)
    Image.new("RGB", (8, 8)).save(folder / "videos" / "both mouth.gif")
    (folder / "videos" / "notes.txt").write_text("not a video")


def check_links(folder: Path, page: Page) -> None:
    """Every link is a relative path inside the folder to a file that exists."""
    for link in page.links:
        assert "://" not in link and not link.startswith(("/", "..")), link
        assert (folder / unquote(link)).is_file(), link


def test_the_report_links_exactly_the_files_the_folder_has(tmp_path: Path) -> None:
    folder = tmp_path / "run"
    make_run(folder)
    add_outputs(folder)
    out = write_report(folder)
    assert out == folder / REPORT_FILE
    page = Page(out.read_text())
    assert page.open == ["html"] or page.open == []  # every other tag closed in order
    check_links(folder, page)
    assert sorted(page.links) == sorted(
        ["fig4.png", "retention.png", "videos/policy-wide.mp4", "videos/both%20mouth.gif"]
    )
    rows = [cells for cells in page.cells if cells and cells[0] in ("0", "1", "2")]
    assert [r[:2] for r in rows] == [["0", "train0"], ["1", "train0"], ["2", "train1"]]
    assert rows[1][2] == "+20.0, -10.0"  # hole offset (mm)
    assert [r[10] for r in rows] == ["1.1", "94.0", "1.3"] and [r[11] for r in rows] == [
        "success", "miss", "success"
    ]  # fmt: skip
    assert [r[5:7] for r in rows] == [
        ["45 / 3 / 9", "0"],
        ["45 / 3 / 18", "1"],
        ["45 / 3 / 27", "2"],
    ]
    text = out.read_text()
    assert (
        "Rollouts on the arm: 130 start, 135 sample, 12 probe, 54 visit (331 while learning)"
        in text
    )
    assert "Stopped at a limit while learning: 3 (3 sample, 0 probe, 0 visit)" in text
    assert "Seconds on the arm" not in text  # a simulator
    assert "on the arm's model" not in text  # its visits ran on the arm
    assert "Forgotten (succeeded after their own S-step, missed at the end): [0]" in text
    settings = {cells[0]: cells[1] for cells in page.cells if len(cells) == 2}
    assert settings["stream.policy.steps"] == "3000" and settings["seed"] == "3"
    assert settings["task.urdf"] == json.dumps(KUKA)


def test_an_interrupted_run_names_what_is_missing_and_links_nothing(tmp_path: Path) -> None:
    folder = tmp_path / "run"
    make_run(folder, finished=False)
    text = report_html(folder)
    page = Page(text)
    assert page.links == []
    assert "2 of 3 conditions completed (interrupted run" in text
    for command in ("scripts/evaluate.py", "scripts/retention.py", "scripts/render.py"):
        assert f"python {command} --run DIR" in text
    rows = [cells for cells in page.cells if cells and cells[0] in ("0", "1", "2")]
    assert [r[0] for r in rows] == ["0", "1"]


def test_the_script_writes_the_report_or_one_error_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = tmp_path / "run"
    make_run(folder)
    add_outputs(folder)
    monkeypatch.setattr(sys, "argv", ["report.py", "--run", str(folder), "--no-make"])
    runpy.run_path(str(SCRIPT), run_name="__main__")
    assert (folder / REPORT_FILE).is_file()
    check_links(folder, Page((folder / REPORT_FILE).read_text()))
    monkeypatch.setattr(sys, "argv", ["report.py", "--run", str(tmp_path / "absent")])
    with pytest.raises(SystemExit) as exit_info:
        runpy.run_path(str(SCRIPT), run_name="__main__")
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: "), err
