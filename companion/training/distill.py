"""Train CPU-sized students on many crops (GPU or CPU), distilled from a large teacher or not.

    python -m companion.training.distill --shared .pack/shared --device cuda --workers 15 \\
        --teacher-seconds 210 --student-seconds 200 --out-dir /tmp/distill
    python -m companion.training.distill --shared .pack/shared --device cuda --workers 15 \\
        --students g40,gf32,gl48,w40 --init companion/models/slz-density-v2.onnx \\
        --student-seconds 480 --out-dir /tmp/students         # no d student: no teacher
    python -m companion.training.distill --shared .pack/shared --device cuda --workers 15 \
        --students df32,kl48 --teacher-init 40=companion/models/slz-density-v4.onnx \
        --init df32=WF32.onnx,kl48=WL48.onnx --student-seconds 470 --out-dir /tmp/taught

Two phases over one stream of training crops (the sources of :mod:`companion.training.train`:
the real photos, the synthetic top-down crowds and the hard negatives, at the given shares):

1. **Teacher** (:class:`companion.training.model.TeacherNet`, about 5.6 M parameters) and every
   student learn the ground-truth maps with the weighted cross-entropy of the shipped model
   (:func:`companion.training.train.loss`, biased toward "occupied"). With ``--teacher-init
   ARCH=FILE`` an exported model (the shipped version 4, say) is the teacher instead, frozen and
   run mirrored by its own ``companion.border_px`` as the service runs it, and there is no phase 1.
2. **Distillation**: the teacher is frozen; each student named ``d<width>`` learns
   ``alpha`` x that loss on the ground truth plus ``1 - alpha`` x the plain cross-entropy toward the
   teacher's probability map (``k<width>``: a Huber loss toward its log-odds instead); each student
   named ``g<width>`` (the control) keeps learning the ground truth alone, so the two differ only
   by the teacher. Without a ``d`` or ``k`` student there is no teacher and no phase 1: the
   students learn the ground truth for ``--student-seconds``.

Students are named ``<kind><arch><width>[-tag]`` (:class:`StudentSpec`): kind ``d`` distilled, ``k``
distilled on log-odds (:func:`logit_distill_loss`), ``g`` ground truth, ``w`` ground truth
warm-started from ``--init`` (an exported model of the same network: one file for every ``w``
student, or ``NAME=FILE`` pairs, one per ``w`` student, where a pair may also start a ``d`` or
``k`` student; batch norms keep the file's statistics, learning rate x ``--init-lr-scale``); arch
none for the shipped C-CNN, ``f`` for the cheaper :class:`companion.training.model.SLZFastNet`,
``l`` for its depthwise body; a tag tells apart students of one network, which ``--alpha-of
NAME=ALPHA`` may give their own weight of the ground truth (``--students kl48,kl48-a25 --alpha-of
kl48-a25=0.25``: the same start, the same crops, a quarter of the loss on the ground truth).

Each phase stops at its step count or its wall-clock budget, whichever comes first, with a cosine
learning rate over that progress (a time budget makes the run fit a lent GPU's lease; steps make it
deterministic). Crops are made on the CPU in ``--workers`` processes (the synthetic compositor is
the bottleneck: about 12-22 ms per 256x256 crop on one core), so a GPU run is bound by crop making.

Writes to ``--out-dir``: ``teacher.pt`` (half-precision state dict), ``students.pt`` (every student's
state dict, width and steps), ``history.json`` (losses and crops per second) and, per student,
``slz-<name>.onnx`` unless ``--no-export``. The ONNX files carry no threshold: calibrate them
(:mod:`companion.training.calibrate`) on the machine that holds ``../shared``'s validation sets.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import re
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from companion.evaluation import datasets as D
from companion.training import model as M
from companion.training.export import export_onnx
from companion.training.negatives import check_kinds
from companion.training.train import CropSource, all_sources, check_shares, loss, normalise, raw_batch, resolve_device

log = logging.getLogger("companion.training.distill")


class CropStream(torch.utils.data.IterableDataset):
    """Endless batches from ``sources`` (uint8 crops, float targets: see ``raw_batch``); each worker
    process draws from its own seeded generator."""

    def __init__(self, sources: list[CropSource], batch: int, crop: int, seed: int) -> None:
        super().__init__()
        self.sources, self.batch, self.crop, self.seed = sources, batch, crop, seed

    def __iter__(self) -> Iterator[tuple[torch.Tensor, torch.Tensor]]:
        torch.set_num_threads(1)
        info = torch.utils.data.get_worker_info()
        rng = np.random.default_rng([self.seed, 0 if info is None else info.id + 1])
        while True:
            xs, ys = raw_batch(self.sources, self.batch, self.crop, rng)
            yield torch.from_numpy(xs), torch.from_numpy(ys)


def batches(stream: CropStream, workers: int, pin: bool) -> Iterator[tuple[torch.Tensor, torch.Tensor]]:
    if workers == 0:
        yield from stream
        return
    ctx = "fork" if "fork" in torch.multiprocessing.get_all_start_methods() else None
    loader = torch.utils.data.DataLoader(stream, batch_size=None, num_workers=workers, pin_memory=pin,
                                         prefetch_factor=4, persistent_workers=True, multiprocessing_context=ctx)
    yield from loader


@dataclass
class Learner:
    """One network, its optimiser and its running record."""

    name: str
    net: torch.nn.Module
    lr: float
    opt: torch.optim.Optimizer = field(init=False)
    steps: int = 0
    losses: list[float] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.opt = torch.optim.AdamW(self.net.parameters(), lr=self.lr, weight_decay=1e-4)

    def step(self, batch_loss: torch.Tensor, lr_factor: float) -> None:
        for g in self.opt.param_groups:
            g["lr"] = self.lr * lr_factor
        self.opt.zero_grad(set_to_none=True)
        batch_loss.backward()
        self.opt.step()
        self.steps += 1
        self.losses.append(float(batch_loss.detach()))


def lr_factor(progress: float, step: int, warm: int) -> float:
    """Linear warm-up over ``warm`` steps, then cosine from 1 to 0 over ``progress`` in [0, 1]."""
    return min(1.0, (step + 1) / warm) * 0.5 * (1 + math.cos(math.pi * min(1.0, progress)))


def distill_loss(student: torch.Tensor, target: torch.Tensor, teacher_p: torch.Tensor, pos_weight: float,
                 alpha: float) -> torch.Tensor:
    """``alpha`` x the shipped loss on the ground truth + ``1 - alpha`` x BCE toward the teacher's map.

    The teacher learnt the same weighted loss, so its probability already leans toward "occupied"
    (see :func:`companion.training.train.loss`); the second term is unweighted so the lean is not
    applied twice.
    """
    return alpha * loss(student, target, pos_weight) + (1 - alpha) * F.binary_cross_entropy_with_logits(
        student, teacher_p)


LOGIT_RANGE = (-9.0, 6.0)


def logit_distill_loss(student: torch.Tensor, target: torch.Tensor, teacher_p: torch.Tensor, pos_weight: float,
                       alpha: float) -> torch.Tensor:
    """``alpha`` x the shipped loss on the ground truth + ``1 - alpha`` x a Huber loss between the
    student's and the teacher's log-odds (both clipped to :data:`LOGIT_RANGE`).

    Why not the cross-entropy of :func:`distill_loss`: the service thresholds the map at a
    probability near 0.013 (log-odds -4.3), where a cross-entropy toward the teacher's probability
    barely pulls (its gradient is the difference of two small probabilities); on log-odds an error
    at -4.3 weighs what it weighs at 0, so the student learns the teacher's faint evidence of a
    small person, which is what decides "occupied" there. Clipping stops the student chasing the
    teacher's certainty far from the threshold.
    """
    lo, hi = LOGIT_RANGE
    eps = 1e-6
    t_logit = torch.logit(teacher_p.clamp(eps, 1 - eps)).clamp(lo, hi)
    return alpha * loss(student, target, pos_weight) + (1 - alpha) * F.smooth_l1_loss(student.clamp(lo, hi), t_logit)


@dataclass(frozen=True)
class StudentSpec:
    """One ``--students`` entry: ``<kind><arch><width>[-tag]``.

    kind: ``d`` distilled from the teacher (``k``: on its log-odds), ``g`` ground truth only (the
    control), ``w`` ground truth only, warm-started from ``--init`` (an exported model of the same
    architecture and width; ``d`` and ``k`` students may be given one too). arch: none for the
    shipped C-CNN (:class:`companion.training.model.SLZDensityNet`), ``f`` for
    :class:`companion.training.model.SLZFastNet`, ``l`` for its depthwise body. tag: letters and
    digits naming one of several students of the same network in one run (``kl48-a25``), so that
    they can differ by ``--alpha-of`` or ``--init``."""

    name: str
    kind: str
    arch: str
    width: int

    def build(self) -> torch.nn.Module:
        return M.student(self.arch, self.width)


def parse_students(spec: str) -> list[StudentSpec]:
    """``"d40,k40,g40,gf32,w40,kl48-a25"`` -> one :class:`StudentSpec` each; width 8-256."""
    out = []
    for item in (s.strip() for s in spec.split(",") if s.strip()):
        m = re.fullmatch(r"([dkgw])([fl]?)(\d+)(-[a-z0-9]{1,12})?", item)
        if m is None or not 8 <= int(m.group(3)) <= 256:
            raise ValueError(f"--students: {item!r} is not <d|k|g|w>[f|l]<width>[-tag] with a width of 8-256 "
                             "and a tag of 1-12 lower-case letters and digits")
        out.append(StudentSpec(item, m.group(1), m.group(2), int(m.group(3))))
    if len({s.name for s in out}) != len(out):
        raise ValueError(f"--students names a student twice: {spec!r}")
    return out


def named_pairs(arg: str | None, option: str, value: str, names: list[str], kinds: str) -> list[tuple[str, str]]:
    """``option``'s ``NAME=VALUE,...`` pairs, each NAME one of ``names`` (the students of
    ``kinds``, named in the error), each VALUE non-empty: what ``--init`` and ``--alpha-of`` share."""
    pairs = []
    for item in (i.strip() for i in (arg or "").split(",") if i.strip()):
        name, sep, text = item.partition("=")
        if not sep or not name or not text:
            raise ValueError(f"{option}: {item!r} is not NAME={value}")
        if name not in names:
            raise ValueError(f"{option} names {name!r}, which is not {kinds} student of --students "
                             f"({', '.join(names) or 'none'})")
        pairs.append((name, text))
    return pairs


def parse_inits(arg: str | None, students: list[StudentSpec]) -> dict[str, Path]:
    """``--init``: one exported model for every ``w`` student, or ``NAME=FILE,NAME=FILE`` naming one
    per ``w`` student (``wf32=v3.onnx,w40=v2.onnx``). Every ``w`` student gets a file that exists.
    A pair may also name a ``d`` or ``k`` student: it then starts from that file and learns from
    the teacher (a cheap network already trained, taught on by a better one)."""
    warm = [s.name for s in students if s.kind == "w"]
    startable = [s.name for s in students if s.kind in ("w", "d", "k")]
    if not arg:
        if warm:
            raise ValueError("w students need --init, an exported model file (or NAME=FILE pairs)")
        return {}
    if "=" not in arg:
        if not warm:  # a start nobody takes is a mistake in the command, not something to train past
            raise ValueError(f"--init is given but --students names no w student to start from it: {arg!r}")
        inits = {name: Path(arg) for name in warm}
    else:
        inits = {name: Path(file) for name, file in named_pairs(arg, "--init", "FILE", startable, "a w, d or k")}
        missing = sorted(set(warm) - set(inits))
        if missing:
            raise ValueError(f"--init gives no file for the w student(s) {', '.join(missing)}")
    for name, path in inits.items():
        if not path.is_file():
            raise ValueError(f"--init for {name}: {path} is not a file")
    return inits


def parse_alphas(arg: str | None, students: list[StudentSpec], default: float) -> dict[str, float]:
    """``--alpha-of NAME=A,...``: the weight of the ground truth for each ``d`` or ``k`` student,
    ``--alpha`` (``default``) for those not named. One run can then compare how much each student
    learns from the teacher on the very same crops, which two runs cannot."""
    taught = [s.name for s in students if s.kind in ("d", "k")]
    alphas = dict.fromkeys(taught, default)
    for name, value in named_pairs(arg, "--alpha-of", "ALPHA", taught, "a d or k"):
        try:
            alpha = float(value)
        except ValueError:
            alpha = math.nan
        if not 0 <= alpha <= 1:  # NaN fails this too
            raise ValueError(f"--alpha-of {name}: the weight must be in [0, 1], got {value!r}")
        alphas[name] = alpha
    return alphas


def needs_teacher(students: list[StudentSpec]) -> bool:
    return any(s.kind in ("d", "k") for s in students)


@dataclass(frozen=True)
class FrozenTeacher:
    """``--teacher-init ARCH=FILE``: an exported model (``40`` the C-CNN of width 40, ``f32``, ...)
    as the teacher, frozen; no phase 1. Run as the service runs it: mirrored by the file's
    ``companion.border_px`` (version 4's 16 px), so its zero-padding bands at a crop's edge (what
    the border fixes in the service) are not taught to the students."""

    arch: str
    width: int
    path: Path
    border: int

    def build(self) -> torch.nn.Module:
        net = M.student(self.arch, self.width)
        M.load_folded_onnx(net, str(self.path))
        return net


def parse_teacher_init(arg: str) -> FrozenTeacher:
    spec, sep, file = arg.partition("=")
    m = re.fullmatch(r"([fl]?)(\d+)", spec.strip())
    if not sep or m is None or not file:
        raise ValueError(f"--teacher-init: {arg!r} is not ARCH=FILE (ARCH: [f|l]<width>, e.g. 40=v4.onnx)")
    path = Path(file)
    from companion.pipeline.density import DensityModel, DensityModelError

    try:
        # The service's runner reads and checks the border (present, an integer in range, a
        # multiple of the model's stride), so the teacher is mirrored by what the service uses.
        border = DensityModel(path, threads=1).spec.border_px
    except DensityModelError as exc:
        raise ValueError(f"--teacher-init: {exc}") from None
    teacher = FrozenTeacher(m.group(1), int(m.group(2)), path, border)
    teacher.build()  # a misfit (architecture, width) is an error now, not after the data loads
    return teacher


def mirrored(net: torch.nn.Module, x: torch.Tensor, border: int) -> torch.Tensor:
    """``net``'s stride-4 logits for ``x`` mirrored by ``border`` pixels (reflect without repeating
    the edge, OpenCV's BORDER_REFLECT_101 as in the runner), cropped back to ``x``'s cells."""
    if border == 0:
        return net(x)
    c = border // M.STRIDE
    y = net(F.pad(x, (border, border, border, border), mode="reflect"))
    return y[..., c:y.shape[-2] - c, c:y.shape[-1] - c]


class Phase:
    """Progress of one phase: done at ``steps`` or ``seconds`` (0 = no limit), whichever first."""

    def __init__(self, steps: int, seconds: float) -> None:
        if steps <= 0 and seconds <= 0:
            raise ValueError("a phase needs a step count or a time budget")
        self.steps, self.seconds, self.t0, self.k = steps, seconds, time.monotonic(), 0

    @property
    def progress(self) -> float:
        p = [self.k / self.steps] if self.steps > 0 else []
        p += [(time.monotonic() - self.t0) / self.seconds] if self.seconds > 0 else []
        return max(p)

    def done(self) -> bool:
        return self.progress >= 1.0


def run(args: argparse.Namespace) -> dict[str, object]:
    device = resolve_device(args.device)
    cuda = device.type == "cuda"
    torch.manual_seed(args.seed)
    if cuda:
        torch.backends.cudnn.benchmark = True
        torch.backends.cuda.matmul.allow_tf32 = True
        torch.backends.cudnn.allow_tf32 = True
    out = Path(args.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.monotonic()
    # OpenCV's and torch's thread pools do not survive fork(): single-threaded OpenCV before the
    # data is loaded, and the crop workers started (first batch drawn) before any network exists.
    cv2.setNumThreads(1)
    sources = all_sources(Path(args.shared), args.synthetic_share, args.negative_share, args.max_images, args.seed,
                          args.negative_kinds)
    t_load = time.monotonic() - t_start
    stream = batches(CropStream(sources, args.batch, args.crop, args.seed), args.workers, cuda)
    first: tuple[torch.Tensor, torch.Tensor] | None = next(stream)
    torch.set_num_threads(args.threads)
    specs = parse_students(args.students)
    use_teacher = needs_teacher(specs)
    frozen = parse_teacher_init(args.teacher_init) if args.teacher_init and use_teacher else None
    teacher_net = frozen.build() if frozen is not None else M.TeacherNet(args.teacher_width)
    teacher = Learner("teacher", teacher_net.to(device), args.teacher_lr) if use_teacher else None
    t_border = frozen.border if frozen is not None else 0
    inits = parse_inits(args.init, specs)
    alphas = parse_alphas(args.alpha_of, specs, args.alpha)
    students, warm = [], set()
    for spec in specs:
        net = spec.build()
        lr = args.lr
        if spec.name in inits:  # every w student, and a d student given a start
            init = inits[spec.name]
            log.info("%s starts from %s (%d convolutions)", spec.name, init, M.load_folded_onnx(net, str(init)))
            lr *= args.init_lr_scale
            warm.add(spec.name)
        students.append(Learner(spec.name, net.to(device), lr))
    mem = torch.channels_last if cuda else torch.contiguous_format
    learners = ([teacher] if teacher is not None else []) + students
    for lrn in learners:
        # Module.to accepts memory_format, but torch's stubs list no overload with it.
        cast(Any, lrn.net).to(memory_format=mem).train()
        if lrn.name in warm:
            M.freeze_batchnorm(lrn.net)  # keep the start: see load_folded_onnx
    log.info("teacher %s parameters; students %s", M.count_parameters(teacher.net) if teacher else "no",
             {s.name: M.count_parameters(s.net) for s in students})
    amp = torch.autocast("cuda", dtype=torch.bfloat16) if cuda else torch.autocast("cpu", enabled=False)
    history: dict[str, object] = {"load_s": round(t_load, 1), "args": vars(args),
                                  "teacher": str(frozen.path) if frozen is not None else None,
                                  "alphas": alphas}  # each taught student's weight, as trained
    by_name = {sp.name: sp for sp in specs}

    def save_students(tag: str) -> None:
        torch.save({s.name: {"state_dict": {k: v.cpu() for k, v in s.net.state_dict().items()},
                             "arch": by_name[s.name].arch, "width": by_name[s.name].width, "steps": s.steps,
                             "tag": tag} for s in students}, out / "students.pt")

    phases = ((args.teacher_steps, args.teacher_seconds), (args.student_steps, args.student_seconds))
    for phase_no, (steps, seconds) in enumerate(phases, 1):
        if phase_no == 1 and (teacher is None or frozen is not None):
            history["phase1"] = {"steps": 0, "seconds": 0.0, "crops": 0, "crops_per_s": 0.0}
            continue  # no distilled student (no teacher), or a teacher already trained: nothing to train
        ph = Phase(steps, seconds)
        if phase_no == 2 and teacher is not None:
            teacher.net.eval()
        crops = 0
        t_save = time.monotonic()
        while not ph.done():
            x, y = first if first is not None else next(stream)
            first = None
            x = normalise(x.to(device, non_blocking=True)).contiguous(memory_format=mem)
            y = y.to(device, non_blocking=True)
            f = lr_factor(ph.progress, ph.k, args.warmup)
            t_p = None
            with amp:  # forward passes in bf16 on a GPU; losses and backward passes outside autocast
                if phase_no == 1 and teacher is not None:
                    t_logits = teacher.net(x)
                elif teacher is not None:
                    with torch.no_grad():
                        t_p = torch.sigmoid(mirrored(teacher.net, x, t_border).float())
                s_logits = [s.net(x) for s in students]
            if phase_no == 1 and teacher is not None:
                teacher.step(loss(t_logits.float(), y, args.pos_weight), f)
            for s, logits in zip(students, s_logits):
                if t_p is not None and by_name[s.name].kind == "d":
                    s.step(distill_loss(logits.float(), y, t_p, args.pos_weight, alphas[s.name]), f)
                elif t_p is not None and by_name[s.name].kind == "k":
                    s.step(logit_distill_loss(logits.float(), y, t_p, args.pos_weight, alphas[s.name]), f)
                else:
                    s.step(loss(logits.float(), y, args.pos_weight), f)
            ph.k += 1
            crops += len(x)
            if ph.k % args.log_every == 0:
                el = time.monotonic() - ph.t0
                recent = {lrn.name: round(float(np.mean(lrn.losses[-args.log_every:])), 4)
                          for lrn in ([teacher] if phase_no == 1 and teacher else []) + students}
                log.info("phase %d step %d %.0f%% %.0f crops/s lr x%.2f %s", phase_no, ph.k, 100 * ph.progress,
                         crops / el, f, recent)
            if time.monotonic() - t_save > args.save_every_s:
                save_students(f"phase {phase_no} step {ph.k}")
                t_save = time.monotonic()
        el = time.monotonic() - ph.t0
        history[f"phase{phase_no}"] = {"steps": ph.k, "seconds": round(el, 1), "crops": crops,
                                       "crops_per_s": round(crops / max(el, 1e-9), 1)}
        log.info("phase %d done: %d steps, %d crops in %.0f s", phase_no, ph.k, crops, el)
        if phase_no == 1 and teacher is not None and frozen is None:
            torch.save({k: v.half().cpu() for k, v in teacher.net.state_dict().items()}, out / "teacher.pt")
        save_students(f"phase {phase_no} done")
    history["losses"] = {lrn.name: [round(float(np.mean(lrn.losses[i:i + 50])), 4)
                                    for i in range(0, len(lrn.losses), 50)] for lrn in learners}
    history["device"] = torch.cuda.get_device_name(device) if cuda else f"cpu ({os.cpu_count()} cores)"
    history["total_s"] = round(time.monotonic() - t_start, 1)
    (out / "history.json").write_text(json.dumps(history, indent=1) + "\n")
    if not args.no_export:
        for s in students:
            net = cast(Any, s.net).float().cpu().eval().to(memory_format=torch.contiguous_format)
            kind = by_name[s.name].kind
            how = (f"alpha={alphas[s.name]}" + (f" teacher={frozen.path.name}" if frozen is not None else "")
                   + (" on log-odds" if kind == "k" else "")
                   if kind in ("d", "k") else "ground truth only (no teacher)")
            if s.name in inits:
                how += f", warm-started from {inits[s.name].name} at lr x{args.init_lr_scale}"
            note = (f"distill {s.name} teacher_steps={history['phase1']['steps']} "  # type: ignore[index]
                    f"student_steps={s.steps} batch={args.batch} synthetic_share={args.synthetic_share} "
                    f"negative_share={args.negative_share}"
                    + (f" negative_kinds={','.join(args.negative_kinds)}" if args.negative_kinds else "")
                    + f" {how} device={history['device']}")
            try:
                export_onnx(net, out / f"slz-{s.name}.onnx", {"companion.training": note})
            except Exception as exc:  # the state dicts are saved: export again where torch.onnx works
                log.warning("export of %s failed (%s); students.pt holds its weights", s.name, exc)
    log.info("total %.0f s", history["total_s"])
    return history


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--shared", default="../shared", help="the shared data, or a pack of it (training.pack)")
    p.add_argument("--out-dir", default="/tmp/slz-distill")
    p.add_argument("--device", default="cpu", help="cpu (default) or cuda[:N]")
    p.add_argument("--workers", type=int, default=0, help="crop-making processes (0: in this process)")
    p.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    p.add_argument("--students", default="d40,g40,d64",
                   help="comma-separated <kind><arch><width>: kind d distilled, k distilled on log-odds, g ground truth only (the "
                        "control), w ground truth from --init; arch none (C-CNN), f (SLZFastNet) or l "
                        "(its depthwise body); e.g. g40,gf32,w40")
    p.add_argument("--init", default=None,
                   help="exported model (.onnx) the w students start from, or NAME=FILE,... one per w student")
    p.add_argument("--init-lr-scale", type=float, default=0.3, help="w students' learning rate x this")
    p.add_argument("--teacher-width", type=int, default=64)
    p.add_argument("--teacher-init", default=None,
                   help="ARCH=FILE: an exported model ([f|l]<width>, e.g. 40=slz-density-v4.onnx) as the teacher, "
                        "frozen and run mirrored by its companion.border_px; no phase 1")
    p.add_argument("--teacher-steps", type=int, default=0, help="0: no step limit (then --teacher-seconds)")
    p.add_argument("--teacher-seconds", type=float, default=0.0)
    p.add_argument("--student-steps", type=int, default=0)
    p.add_argument("--student-seconds", type=float, default=0.0)
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--crop", type=int, default=256)
    p.add_argument("--lr", type=float, default=3e-3, help="students' peak learning rate")
    p.add_argument("--teacher-lr", type=float, default=2e-3)
    p.add_argument("--warmup", type=int, default=200, help="warm-up steps of each phase")
    p.add_argument("--pos-weight", type=float, default=4.0)
    p.add_argument("--alpha", type=float, default=0.5, help="weight of the ground truth in distillation")
    p.add_argument("--alpha-of", default=None,
                   help="NAME=ALPHA,...: another weight of the ground truth for the named d or k students")
    p.add_argument("--synthetic-share", type=float, default=0.35)
    p.add_argument("--negative-share", type=float, default=0.1)
    p.add_argument("--negative-kinds", type=lambda v: [k.strip() for k in v.split(",") if k.strip()], default=None,
                   help="comma-separated hard-negative kinds (training.negatives; default: every kind but the "
                        "opt-in ones, as every shipped model was trained), e.g. landable,no-person-photo")
    p.add_argument("--max-images", type=int, default=0)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--log-every", type=int, default=50)
    p.add_argument("--save-every-s", type=float, default=60.0)
    p.add_argument("--no-export", action="store_true")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    try:
        resolve_device(args.device)
        check_shares(args.synthetic_share, args.negative_share, args.max_images)
        if args.negative_kinds is not None:
            check_kinds(args.negative_kinds)
            if args.negative_share <= 0:
                raise ValueError("--negative-kinds needs --negative-share > 0")
        specs = parse_students(args.students)
        by_name = {sp.name: sp for sp in specs}
        if args.teacher_init and not needs_teacher(specs):
            raise ValueError("--teacher-init is given but --students names no d student to learn from it")
        if args.teacher_init:
            parse_teacher_init(args.teacher_init)
        elif needs_teacher(specs):
            Phase(args.teacher_steps, args.teacher_seconds)
        for name, init in parse_inits(args.init, specs).items():
            M.load_folded_onnx(by_name[name].build(), str(init))  # a clear error now, not after the data loads
        if not 0 < args.init_lr_scale <= 10:
            raise ValueError(f"--init-lr-scale must be in (0, 10], got {args.init_lr_scale}")
        Phase(args.student_steps, args.student_seconds)
        if not 0 <= args.alpha <= 1:
            raise ValueError(f"--alpha must be in [0, 1], got {args.alpha}")
        parse_alphas(args.alpha_of, specs, args.alpha)
        if args.crop % M.STRIDE or args.crop < 32 or args.batch < 1 or args.workers < 0:
            raise ValueError("--crop must be a multiple of 4 and >= 32, --batch >= 1, --workers >= 0")
    except ValueError as exc:
        print(f"companion.training.distill: {exc}", file=sys.stderr)
        return 2
    try:
        run(args)
    except D.DatasetError as exc:
        print(f"companion.training.distill: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
