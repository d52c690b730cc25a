"""`pelvicnav plan`, `pelvicnav guide` and `pelvicnav report` on a simulated patient: the decision,
the target, two frames (the second tracked), the HTML report, and refusals of bad input."""

from __future__ import annotations

import base64
import html.parser
import io
import json
import shutil

import numpy as np
import pytest
from typer.testing import CliRunner

from pelvicnav import BONES
from pelvicnav.cli import app
from pelvicnav.geometry import transforms as tf

runner = CliRunner()


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    """A sampled patient with an open-book dislocation of the left hip (>= 8 mm), its CT, labels
    and two radiographs at the CT's own pose (the truth: every bone at the identity)."""
    from pelvicnav.phantom.case import simulate_case
    from pelvicnav.phantom.population import load_population
    from pelvicnav.workflow.demo import _pick_seed

    pop = load_population("model", subject_ids=(2,))
    vertices = pop.vertices[0]
    root = tmp_path_factory.mktemp("case")
    seed = _pick_seed(vertices, pop.faces, 2)
    truth = simulate_case(vertices, pop.faces, root / "case", subject_id=2, seed=seed,
                          pattern="open-book", bone="left_hip",
                          views=("ap", "oblique30"))  # fmt: skip
    return root, truth


class _Images(html.parser.HTMLParser):
    def __init__(self):
        super().__init__()
        self.sources, self.links = [], []

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "img":
            self.sources.append(a.get("src", ""))
        for key in ("href", "src"):
            if a.get(key, "").startswith(("http:", "https:", "//")):
                self.links.append(a[key])


def _check_report(path) -> int:
    """Every image decodes; nothing is fetched from the network. Returns the image count."""
    from PIL import Image

    parser = _Images()
    parser.feed(path.read_text())
    assert not parser.links
    for src in parser.sources:
        assert src.startswith("data:image/png;base64,")
        Image.open(io.BytesIO(base64.b64decode(src.split(",", 1)[1]))).verify()
    return len(parser.sources)


@pytest.mark.slow
def test_plan_then_guide_two_frames(case, tmp_path):
    root, truth = case
    ct, labels = root / "case" / "ct.nii.gz", root / "case" / "labels.nii.gz"
    plan_dir = tmp_path / "plan"
    res = runner.invoke(app, ["plan", str(ct), "--labels", str(labels), "--out", str(plan_dir)])
    assert res.exit_code == 0, res.output
    doc = json.loads((plan_dir / "plan.json").read_text())
    assert doc["dislocated"] == ["left_hip"] and doc["decision"]["mode"] == "auto"
    assert doc["decision"]["margin"] > 0
    # The target undoes most of the true dislocation (SPM_CC: a few mm, a few degrees off).
    T = np.asarray(doc["targets_from_current"]["left_hip"])
    D = np.asarray(truth["poses_world_from_ct"]["left_hip"])
    centroids = np.asarray(truth["moved_vertices"]).mean(axis=1)  # each bone as in the CT
    c = centroids[1]
    true_target = tf.apply(tf.invert(D), c[None])
    off = np.linalg.norm(tf.apply(T, c[None]) - true_target)
    assert off < max(4.0, 0.5 * np.linalg.norm(true_target - c)), off
    for name in (
        "labels.nii.gz",
        "reduced_ct.nii.gz",
        "rendering.png",
        "contours.png",
        "meshes/left_hip.vtk",
        "meshes/left_hip_target.stl",
        "meshes/sacrum.stl",
    ):
        assert (plan_dir / name).is_file(), name  # fmt: skip
    assert _check_report(_report(plan_dir)) == 2

    session = tmp_path / "session"
    views = str(root / "case" / "views.json")
    for frame, mode in ((1, "first"), (2, "tracking")):
        res = runner.invoke(app, ["guide", str(plan_dir), "--views", views, "--out", str(session)])
        assert res.exit_code == 0, res.output
        record = json.loads((session / f"frame-00{frame}" / "result.json").read_text())
        assert record["mode"] == mode and record["reliable"], record["warnings"]
        for b, c in zip(BONES, centroids, strict=True):  # radiographs of the CT: identities
            err = np.linalg.norm(tf.apply(np.asarray(record["poses"][b]), c[None]) - c)
            assert err < 1.0, (frame, b, err)
        assert "left_hip" in record["residual"]
        for name in (
            "overlay_ap.png",
            "overlay_oblique30.png",
            "transforms/left_hip.tfm",
            "transforms/residual.tfm",
        ):
            assert (session / f"frame-00{frame}" / name).is_file()  # fmt: skip
    # the residual seen now equals the plan's (the images show the CT's dislocation); it is the
    # hip relative to the reference bone, each registered within 1 mm above: within 2 mm
    planned = np.asarray(doc["residual_in_ct"]["left_hip"]["translation_mm"])
    seen = np.asarray(record["residual"]["left_hip"]["translation_mm"])
    assert np.linalg.norm(seen - planned) < 2.0
    session_doc = json.loads((session / "session.json").read_text())
    assert [f["mode"] for f in session_doc["frames"]] == ["first", "tracking"]
    assert _check_report(session / "report.html") == 2 + 2 * 2

    # bad input: nothing is added to the session
    before = sorted(p.name for p in session.iterdir())
    broken = tmp_path / "broken"
    shutil.copytree(root / "case", broken, ignore=shutil.ignore_patterns("*.nii.gz", "meshes"))
    (broken / "ap.npy").unlink()
    res = runner.invoke(app, ["guide", str(plan_dir), "--views", str(broken / "views.json"),
                              "--out", str(session)])  # fmt: skip
    assert res.exit_code == 2 and "cannot read image" in res.output, res.output
    other = json.loads((session / "session.json").read_text()) | {"plan_id": "0123456789abcdef"}
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "session.json").write_text(json.dumps(other))
    res = runner.invoke(app, ["guide", str(plan_dir), "--views", views, "--out", str(foreign)])
    assert res.exit_code == 2 and "belongs to another plan" in res.output, res.output
    assert sorted(p.name for p in session.iterdir()) == before
    assert sorted(p.name for p in foreign.iterdir()) == ["session.json"]


def _report(folder):
    res = runner.invoke(app, ["report", str(folder)])
    assert res.exit_code == 0, res.output
    return folder / "report.html"


@pytest.mark.slow
def test_guide_refuses_a_plan_of_another_ct(case, tmp_path):
    """The plan's CT path now holds another CT: the fingerprint refuses it."""
    from pelvicnav.io.nifti import read_nifti, write_nifti
    from pelvicnav.io.plan import CTReference, Plan, write_plan

    root, _ = case
    ct = tmp_path / "ct.nii.gz"
    shutil.copyfile(root / "case" / "ct.nii.gz", ct)
    plan_dir = tmp_path / "plan"
    plan_dir.mkdir()
    shutil.copyfile(root / "case" / "labels.nii.gz", plan_dir / "labels.nii.gz")
    data, A = read_nifti(ct)
    write_plan(plan_dir, Plan(ct=CTReference.of(ct, data, A), dislocated=("left_hip",),
                              targets={"left_hip": np.eye(4)}))  # fmt: skip
    data[10, 10, 10] += 100  # CT B where CT A was
    write_nifti(ct, data, A)
    res = runner.invoke(app, ["guide", str(plan_dir), "--views", str(root / "case" / "views.json"),
                              "--out", str(tmp_path / "session")])  # fmt: skip
    assert res.exit_code == 2 and "not the CT the plan was made from" in res.output, res.output
    assert not (tmp_path / "session").exists()


def test_plan_bad_input_writes_nothing(tmp_path):
    out = tmp_path / "plan"
    for args, message in (
        ([str(tmp_path / "missing.nii.gz"), "--labels", "x"], "file not found"),
        ([str(tmp_path), "--dislocated", "femur", "--labels", "x"], "--dislocated must be"),
        ([str(tmp_path)], "no DICOM image series"),  # no labels: the ASM would read the CT
    ):
        res = runner.invoke(app, ["plan", *args, "--out", str(out)])
        assert res.exit_code == 2, (args, res.output)
        assert message in " ".join(res.output.split()), res.output
        assert not out.exists()
    res = runner.invoke(app, ["report", str(tmp_path / "nothing")])
    assert res.exit_code == 2 and "not a folder" in res.output


def test_an_unreliable_frame_whose_joints_are_implausible_reads_likely_wrong(tmp_path):
    import json

    from pelvicnav.guide.report import _frame_section

    record = {
        "frame": 3,
        "mode": "first",
        "time": "t",
        "reliable": False,
        "residual": {},
        "warnings": ["left_hip ends with 21% of its joint samples inside another bone"],
    }
    (tmp_path / "result.json").write_text(json.dumps({**record, "verdict": "in question"}))
    assert "Likely wrong" not in _frame_section(tmp_path)
    (tmp_path / "result.json").write_text(json.dumps({**record, "verdict": "implausible"}))
    text = _frame_section(tmp_path)
    assert "UNRELIABLE REGISTRATION" in text and "Likely wrong" in text
