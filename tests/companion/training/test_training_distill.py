"""The GPU training path, run on the CPU: the data pack and teacher-student distillation (issue 13)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from companion.evaluation import datasets as D
from tests import early


@early.batch("pack")
def _pack(folder: Path) -> list[early.Run]:
    """``companion.training.pack.pack`` of ``../shared`` into ``folder / "shared"`` (seconds of
    resizing and encoding photos): a process of its own, started once the session knows it runs
    the test (tests/early.py)."""
    from companion.training.pack import pack
    from tests.conftest import SHARED
    if not (SHARED / "data").is_dir():
        return []  # the test skips (shared_dir)
    return [early.call(folder / "manifest.pickle", pack, str(SHARED), str(folder / "shared"), 0.5, 75, 10)]


@pytest.fixture(scope="module")
def pack_dir(shared_dir: Path) -> Path:
    """``../shared`` packed with ShanghaiTech B at half size, JPEG quality 75, every tenth layout."""
    (run,) = early.result("pack")[1]
    assert json.loads(run.args[-1])[0] == str(shared_dir)
    early.returned("pack")  # its manifest, written to pack.json too
    return Path(json.loads(run.args[-1])[1])


@pytest.mark.started_early("pack")
def test_pack_is_read_by_the_same_loaders_with_the_same_splits(pack_dir: Path, shared_dir: Path) -> None:
    from companion.evaluation.compositor import load_layouts
    from companion.training.pack import shb_scale

    assert shb_scale(pack_dir) == 0.5 and shb_scale(shared_dir) == 1.0
    # The semantic-drone split is by sorted index: the same photos train, the same are held out.
    for split in ("train", "val"):
        assert [s.name for s in D.semantic_drone(pack_dir, split)] == [s.name for s in D.semantic_drone(shared_dir, split)]
    # ShanghaiTech B: every training photo, half the size, head points scaled alike.
    full, half = D.shanghaitech_b(shared_dir, "train"), D.shanghaitech_b(pack_dir, "train")
    assert [s.name for s in half] == [s.name for s in full]
    assert half[7].image().shape[:2] == (full[7].image().shape[0] // 2, full[7].image().shape[1] // 2)
    np.testing.assert_allclose(half[7].points, full[7].points * 0.5, atol=1e-3)
    # DroneCrowd: the training frames with their own head points; layouts of the training split only.
    assert [len(s.points) for s in D.dronecrowd_frames(pack_dir, D.DRONECROWD_TRAIN)] == \
        [len(s.points) for s in D.dronecrowd_frames(shared_dir, D.DRONECROWD_TRAIN)]
    assert sorted(load_layouts(pack_dir, "train").sequences) == sorted(load_layouts(shared_dir, "train").sequences)
    assert not (pack_dir / "data" / "dronecrowd" / "frames" / "img017").exists()  # the held-out frame stays out
    assert not (pack_dir / "data" / "mall").exists() and not (pack_dir / "data" / "shanghaitech_b" / "test_data").exists()
    manifest = json.loads((pack_dir / "pack.json").read_text())
    assert manifest["shanghaitech_b"] == {"scale": 0.5, "quality": 75, "images": 400}
    assert sum(p.stat().st_size for p in pack_dir.rglob("*") if p.is_file()) < 58 * 2**20  # fits a GPU call


def test_training_from_a_pack_covers_the_same_person_sizes(pack_dir: Path) -> None:
    pytest.importorskip("torch", reason="training needs torch (the 'train' extra; not a dev dependency)")
    from companion.training.train import load_sources

    shb = {s.name: s for s in load_sources(pack_dir, max_images=2)}["shanghaitech_b"]
    assert shb.aug.scale == pytest.approx((0.5, 1.8))  # 0.25-0.9 of the full-size photo


def test_pack_rejects_bad_arguments_and_a_bad_manifest(tmp_path: Path, shared_dir: Path, capsys) -> None:
    from companion.training.pack import main, shb_scale

    assert main(["--shared", str(shared_dir), "--out", str(tmp_path / "p"), "--shb-scale", "0"]) == 2
    assert "--shb-scale" in capsys.readouterr().err
    assert main(["--shared", str(tmp_path / "nowhere"), "--out", str(tmp_path / "p")]) == 2
    assert "missing" in capsys.readouterr().err
    (tmp_path / "pack.json").write_text('{"shanghaitech_b": {}}')
    with pytest.raises(D.DatasetError, match="not a training pack"):
        shb_scale(tmp_path)


def test_distillation_runs_both_phases_on_cpu_and_exports_students(tmp_path: Path, pack_dir: Path) -> None:
    """The GPU command's code path on the CPU, with crop-making worker processes: a teacher, one
    distilled student and its control; every student exports and loads through the runner."""
    torch = pytest.importorskip("torch", reason="training needs torch (the 'train' extra; not a dev dependency)")
    import onnx

    from companion.pipeline.density import DensityModel
    from companion.training.distill import main
    from companion.training.model import SLZDensityNet

    out = tmp_path / "d"
    rc = main(["--shared", str(pack_dir), "--out-dir", str(out), "--workers", "1", "--threads", "1",
               "--students", "d16,g16", "--teacher-width", "8", "--teacher-steps", "3", "--student-steps", "2",
               "--batch", "2", "--crop", "64", "--max-images", "3", "--log-every", "1"])
    assert rc == 0
    hist = json.loads((out / "history.json").read_text())
    assert hist["phase1"]["steps"] == 3 and hist["phase2"]["steps"] == 2 and hist["phase1"]["crops"] == 6
    assert len(hist["losses"]["teacher"]) == 1 and np.isfinite(hist["losses"]["d16"]).all()
    students = torch.load(out / "students.pt")
    assert {k: (v["width"], v["steps"]) for k, v in students.items()} == {"d16": (16, 5), "g16": (16, 5)}
    net = SLZDensityNet(16)
    net.load_state_dict(students["d16"]["state_dict"])  # the saved weights are a whole student
    assert (out / "teacher.pt").is_file()
    for name in ("d16", "g16"):
        m = DensityModel(out / f"slz-{name}.onnx", threads=1)
        assert m(np.zeros((64, 96, 3), np.uint8)).shape == (16, 24)
        note = {p.key: p.value for p in onnx.load(str(out / f"slz-{name}.onnx")).metadata_props}["companion.training"]
        assert f"distill {name}" in note and "device=cpu" in note
        assert ("alpha=0.5" in note) == (name == "d16") and ("no teacher" in note) == (name == "g16")


def _fitted_probability(loss_fn, teacher, lr: float, steps: int) -> float:
    """The mean probability a free map of logits settles at under ``loss_fn`` with alpha = 0 (the
    teacher's term alone; an all-empty ground truth), by plain gradient descent from p = 0.5."""
    import torch

    target = torch.zeros_like(teacher)
    logits = torch.zeros_like(teacher, requires_grad=True)
    opt = torch.optim.SGD([logits], lr=lr)
    for _ in range(steps):
        opt.zero_grad()
        loss_fn(logits, target, teacher, 4.0, 0.0).backward()
        opt.step()
    return float(torch.sigmoid(logits.detach()).mean())


def test_distillation_loss_pulls_toward_the_teacher() -> None:
    torch = pytest.importorskip("torch", reason="training needs torch (the 'train' extra; not a dev dependency)")
    from companion.training.distill import distill_loss

    target = torch.zeros(1, 1, 4, 4)
    teacher = torch.full((1, 1, 4, 4), 0.3)
    # With alpha = 0 the optimum is the teacher's probability; with alpha = 1 it ignores the teacher.
    assert _fitted_probability(distill_loss, teacher, lr=5.0, steps=300) == pytest.approx(0.3, abs=0.01)
    a = distill_loss(torch.zeros(1, 1, 4, 4), target, teacher, 4.0, 1.0)
    b = distill_loss(torch.zeros(1, 1, 4, 4), target, torch.full((1, 1, 4, 4), 0.9), 4.0, 1.0)
    assert float(a) == pytest.approx(float(b))


def test_log_odds_distillation_pulls_toward_the_teachers_faint_evidence() -> None:
    """At the service's threshold (p near 0.013) the cross-entropy toward the teacher hardly pulls;
    the log-odds loss pulls there as hard as anywhere, and converges to the teacher's probability."""
    torch = pytest.importorskip("torch", reason="training needs torch (the 'train' extra; not a dev dependency)")
    from companion.training.distill import distill_loss, logit_distill_loss

    target = torch.zeros(1, 1, 4, 4)
    teacher = torch.full((1, 1, 4, 4), 0.02)  # faint evidence of a person, above a 0.013 threshold
    grads = {}
    for name, fn in (("bce", distill_loss), ("logit", logit_distill_loss)):
        s = torch.full((1, 1, 4, 4), -6.0, requires_grad=True)  # the student says p = 0.0025: "free"
        fn(s, target, teacher, 4.0, 0.0).backward()
        grads[name] = float(s.grad.abs().mean())
    assert grads["logit"] > 20 * grads["bce"]
    assert _fitted_probability(logit_distill_loss, teacher, lr=20.0, steps=400) == pytest.approx(0.02, rel=0.02)


def test_distillation_rejects_bad_arguments(tmp_path: Path, capsys) -> None:
    pytest.importorskip("torch", reason="training needs torch (the 'train' extra; not a dev dependency)")
    from companion.training.distill import main, parse_students

    assert [(s.name, s.kind, s.arch, s.width) for s in parse_students("d40, g40,gf32,wl48,kl48,kl48-a25")] == \
        [("d40", "d", "", 40), ("g40", "g", "", 40), ("gf32", "g", "f", 32), ("wl48", "w", "l", 48),
         ("kl48", "k", "l", 48), ("kl48-a25", "k", "l", 48)]
    base = ["--shared", str(tmp_path), "--out-dir", str(tmp_path / "o"), "--teacher-steps", "1", "--student-steps", "1"]
    for extra, says in ((["--students", "x40"], "<d|k|g|w>"), (["--students", "gq40"], "<d|k|g|w>"),
                        (["--students", "w40"], "need --init"),
                        (["--students", "w40", "--init", str(tmp_path / "none.onnx")], "is not a file"),
                        (["--students", "w40,wf32", "--init", f"w40={tmp_path}"], "no file for the w student(s) wf32"),
                        (["--students", "w40", "--init", f"g40={tmp_path}"], "not a w, d or k student"),
                        (["--students", "w40", "--init", "w40="], "is not NAME=FILE"),
                        (["--students", "g40", "--init", str(tmp_path)], "no w student"),
                        (["--students", "g40", "--init-lr-scale", "0"], "--init-lr-scale"), (["--students", "d40,d40"], "twice"),
                        (["--students", "d4"], "8-256"), (["--alpha", "2"], "--alpha"),
                        (["--students", "kl48-"], "[-tag]"), (["--students", "kl48-A"], "[-tag]"),
                        (["--students", "kl48,kl48-a,kl48-a"], "twice"),
                        (["--students", "d40", "--alpha-of", "g40=0.2"], "not a d or k student"),
                        (["--students", "d40,g40", "--alpha-of", "g40=0.2"], "not a d or k student"),
                        (["--students", "d40", "--alpha-of", "d40"], "is not NAME=ALPHA"),
                        (["--students", "d40", "--alpha-of", "d40=1.5"], "[0, 1]"),
                        (["--students", "d40", "--alpha-of", "d40=nan"], "[0, 1]"),
                        (["--students", "d40", "--alpha-of", "d40=x"], "[0, 1]"),
                        (["--crop", "30"], "--crop"), (["--teacher-steps", "0"], "a phase needs"),
                        (["--synthetic-share", "0.9", "--negative-share", "0.2"], "must be <= 1"),
                        (["--negative-kinds", "landable,puddle"], "unknown hard-negative kind 'puddle'"),
                        (["--negative-share", "0", "--negative-kinds", "landable"], "needs --negative-share > 0")):
        assert main([*base, *extra]) == 2
        assert says in capsys.readouterr().err
    assert main(base) == 2  # no data at --shared: a clear error before any training
    assert "missing" in capsys.readouterr().err
    assert not (tmp_path / "o" / "students.pt").exists()


def _unlike_a_fresh_batchnorm(net) -> None:
    """Random statistics and scales in every batch norm of ``net`` (a fresh one is the identity,
    which would hide a lost or mis-folded start)."""
    import torch

    with torch.no_grad():
        for m in net.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.uniform_(-0.5, 0.5)
                m.running_var.uniform_(0.5, 2.0)
                m.weight.uniform_(0.5, 1.5)


def test_students_without_a_teacher_warm_started_and_cheaper(tmp_path: Path, pack_dir: Path) -> None:
    """No ``d`` student: no teacher, one phase. A ``w`` student starts from an exported model and
    keeps its batch-norm statistics (at a negligible learning rate its export is the start's map);
    the cheaper ``f`` and ``l`` students export and run through the runner like the C-CNN."""
    torch = pytest.importorskip("torch", reason="training needs torch (the 'train' extra; not a dev dependency)")
    from companion.pipeline.density import DensityModel
    from companion.training import model as M
    from companion.training.distill import main
    from companion.training.export import export_onnx

    torch.manual_seed(3)
    start = M.SLZDensityNet(16)
    _unlike_a_fresh_batchnorm(start)  # so a lost start shows
    start.head.bias.data.zero_()  # probabilities mid-range, where a change shows
    init = export_onnx(start, tmp_path / "start.onnx")
    start_f = M.student("f", 16)  # a second w student, of another network, from its own file
    _unlike_a_fresh_batchnorm(start_f)
    start_f.head.bias.data.zero_()
    init_f = export_onnx(start_f, tmp_path / "start-f.onnx")
    out = tmp_path / "s"
    rc = main(["--shared", str(pack_dir), "--out-dir", str(out), "--workers", "0", "--threads", "1",
               "--students", "w16,wf16,gl16", "--init", f"w16={init},wf16={init_f}", "--init-lr-scale", "1e-6",
               "--student-steps", "2", "--batch", "2", "--crop", "64", "--max-images", "3", "--log-every", "1"])
    assert rc == 0
    hist = json.loads((out / "history.json").read_text())
    assert hist["phase1"]["steps"] == 0 and hist["phase2"]["steps"] == 2 and "teacher" not in hist["losses"]
    assert not (out / "teacher.pt").exists()
    saved = torch.load(out / "students.pt")
    assert {k: (v["arch"], v["width"]) for k, v in saved.items()} == {"w16": ("", 16), "wf16": ("f", 16),
                                                                       "gl16": ("l", 16)}
    frame = np.random.default_rng(1).integers(0, 255, (64, 96, 3), np.uint8)
    for name, start_file in (("w16", init), ("wf16", init_f)):
        before = DensityModel(start_file, threads=1)(frame)
        after = DensityModel(out / f"slz-{name}.onnx", threads=1)(frame)
        assert np.abs(after - before).max() < 1e-5 and after.std() > 1e-3, name
    assert DensityModel(out / "slz-gl16.onnx", threads=1)(frame).shape == (16, 24)


def test_an_exported_model_loads_back_exactly_and_a_misfit_is_refused(tmp_path: Path) -> None:
    torch = pytest.importorskip("torch", reason="training needs torch (the 'train' extra; not a dev dependency)")
    import onnxruntime as ort

    from companion.training import model as M
    from companion.training.export import export_onnx

    torch.manual_seed(0)
    x = np.random.default_rng(0).normal(size=(1, 3, 64, 96)).astype(np.float32)
    for arch, width in (("", 16), ("f", 16), ("l", 24)):
        net = M.student(arch, width)
        _unlike_a_fresh_batchnorm(net)
        a = export_onnx(net, tmp_path / f"a{arch}.onnx")
        again = M.student(arch, width)
        assert M.load_folded_onnx(again, str(a)) == sum(isinstance(m, torch.nn.Conv2d) for m in again.modules())
        b = export_onnx(again, tmp_path / f"b{arch}.onnx")
        ya, yb = (ort.InferenceSession(str(p)).run(None, {"input": x})[0] for p in (a, b))
        np.testing.assert_allclose(yb, ya, atol=1e-6)
    with pytest.raises(ValueError, match="convolutions"):
        M.load_folded_onnx(M.student("f", 16), str(tmp_path / "a.onnx"))
    with pytest.raises(ValueError, match=r"\(16, 3, 3, 3\)|is \("):
        M.load_folded_onnx(M.student("f", 24), str(tmp_path / "af.onnx"))
    (tmp_path / "bad.onnx").write_bytes(b"not a model")
    with pytest.raises(ValueError, match="not a readable ONNX model"):
        M.load_folded_onnx(M.student("", 16), str(tmp_path / "bad.onnx"))
    with pytest.raises(ValueError, match="unknown student architecture"):
        M.student("q", 16)


def test_a_trained_model_as_a_frozen_teacher_run_mirrored_and_a_distilled_student_warm_started(
        tmp_path: Path, pack_dir: Path) -> None:
    """``--teacher-init``: an exported model teaches (no phase 1, no teacher.pt), run as the
    service runs it (mirrored by its ``companion.border_px``); a ``d`` student may start from a file."""
    torch = pytest.importorskip("torch", reason="training needs torch (the 'train' extra; not a dev dependency)")
    import onnx

    from companion.pipeline.density import DensityModel
    from companion.training import model as M
    from companion.training.distill import main, mirrored, parse_teacher_init
    from companion.training.export import export_onnx
    from companion.training.train import normalise

    torch.manual_seed(4)
    teacher = M.SLZDensityNet(16)
    _unlike_a_fresh_batchnorm(teacher)
    teacher.head.bias.data.zero_()
    tfile = export_onnx(teacher, tmp_path / "teacher.onnx", {"companion.border_px": 8})
    t = parse_teacher_init(f"16={tfile}")
    assert (t.arch, t.width, t.border) == ("", 16, 8)
    # The teacher's map in training is the runner's map of the same frame, border and all.
    frame = np.random.default_rng(2).integers(0, 255, (64, 96, 3), np.uint8)
    x = normalise(torch.from_numpy(frame.transpose(2, 0, 1)[None].copy()))
    with torch.no_grad():
        p = torch.sigmoid(mirrored(t.build().eval(), x, t.border))[0, 0].numpy()
    runner = DensityModel(tfile, threads=1)
    assert runner.spec.border_px == 8
    np.testing.assert_allclose(p, runner(frame), atol=2e-5)

    student = M.student("l", 16)
    _unlike_a_fresh_batchnorm(student)
    sfile = export_onnx(student, tmp_path / "start.onnx")
    out = tmp_path / "d"
    rc = main(["--shared", str(pack_dir), "--out-dir", str(out), "--workers", "0", "--threads", "1",
               "--students", "dl16,g16,dl16-gt,wl16", "--teacher-init", f"16={tfile}",
               "--init", f"dl16={sfile},dl16-gt={sfile},wl16={sfile}", "--alpha-of", "dl16-gt=1",
               "--student-steps", "2", "--batch", "2", "--crop", "64", "--max-images", "3", "--log-every", "1"])
    assert rc == 0
    # Its own weight reaches the step: taught with alpha 1 (ground truth only), a student learns
    # exactly what the w student of the same start learns on the same crops; at 0.5 it does not.
    weights = {k: v["state_dict"] for k, v in torch.load(out / "students.pt").items()}
    for key, w in weights["wl16"].items():
        assert torch.equal(weights["dl16-gt"][key], w), key
    assert any(not torch.equal(weights["dl16"][k], w) for k, w in weights["wl16"].items())
    notes = {n: {q.key: q.value for q in onnx.load(str(out / f"slz-{n}.onnx")).metadata_props}["companion.training"]
             for n in ("dl16", "dl16-gt")}
    assert "distill dl16-gt " in notes["dl16-gt"] and "alpha=1.0 teacher=teacher.onnx" in notes["dl16-gt"]
    hist = json.loads((out / "history.json").read_text())
    assert hist["alphas"] == {"dl16": 0.5, "dl16-gt": 1.0}
    assert hist["phase1"]["steps"] == 0 and hist["phase2"]["steps"] == 2 and hist["teacher"] == str(tfile)
    assert not (out / "teacher.pt").exists()
    note = {q.key: q.value for q in onnx.load(str(out / "slz-dl16.onnx")).metadata_props}["companion.training"]
    assert "alpha=0.5 teacher=teacher.onnx" in note and "warm-started from start.onnx" in note
    assert DensityModel(out / "slz-dl16.onnx", threads=1)(frame).shape == (16, 24)


def test_a_frozen_teacher_is_checked_before_any_data_loads(tmp_path: Path, capsys) -> None:
    pytest.importorskip("torch", reason="training needs torch (the 'train' extra; not a dev dependency)")
    from companion.training import model as M
    from companion.training.distill import main
    from companion.training.export import export_onnx

    good = export_onnx(M.SLZDensityNet(16), tmp_path / "t.onnx")
    odd = export_onnx(M.SLZDensityNet(16), tmp_path / "odd.onnx", {"companion.border_px": 6})
    (tmp_path / "bad.onnx").write_bytes(b"not a model")
    base = ["--shared", str(tmp_path / "nowhere"), "--out-dir", str(tmp_path / "o"), "--student-steps", "1"]
    for extra, says in ((["--students", "g16", "--teacher-init", f"16={good}"], "no d student"),
                        (["--students", "d16", "--teacher-init", str(good)], "is not ARCH=FILE"),
                        (["--students", "d16", "--teacher-init", f"q16={good}"], "is not ARCH=FILE"),
                        (["--students", "d16", "--teacher-init", f"16={tmp_path / 'none'}"], "does not exist"),
                        (["--students", "d16", "--teacher-init", f"16={tmp_path / 'bad.onnx'}"], "not a loadable ONNX model"),
                        (["--students", "d16", "--teacher-init", f"f16={good}"], "convolutions"),
                        (["--students", "d16", "--teacher-init", f"16={odd}"], "must be a multiple of the model's stride 4"),
                        (["--students", "d16,g16", "--teacher-init", f"16={good}", "--init", f"g16={good}"],
                         "not a w, d or k student")):
        assert main([*base, *extra]) == 2, extra
        assert says in capsys.readouterr().err, extra
