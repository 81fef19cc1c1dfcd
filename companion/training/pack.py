"""Pack the training data into a compact copy of ``../shared`` for a lent GPU machine.

    python -m companion.training.pack --shared ../shared --out .pack/shared

A GPU machine receives a copy of the working tree (64 MiB at most, with what a call carries), and
``../shared`` does not travel with it. The landability training (``companion train-landability``)
reads only the semantic-drone part: carrying ``.pack/shared/data/semantic_drone`` (35 MiB) is
enough for it (``docs/training-runs/2026-11-28-h200-landability-tensor/run.sh``). This writes what :mod:`companion.training.train` and
:mod:`companion.training.distill` read, in the same layout as ``../shared`` so the same loaders
read it (``--shared .pack/shared``), and nothing they do not read:

* semantic drone: every photo (the split is by sorted index, so the held-out fifth must stay for
  the names to line up; its photos are read by no training code), byte for byte, with its class
  maps and person boxes;
* DroneCrowd: the five training frames, ``00112.mat`` whole (their head points), and of the other
  trajectory files only the training split's (:func:`companion.evaluation.compositor.layout_split`),
  every ``--layout-step``-th frame (the compositor draws one frame of a sequence per image, and
  frames 0.4 s apart show nearly the same crowd);
* ShanghaiTech B: the 400 training photos downscaled by ``--shb-scale`` (area filter) and
  re-encoded as JPEG ``--shb-quality``, their head points scaled alike; ``pack.json`` records the
  factor and the training loader widens its scale augmentation and target sigmas by the inverse, so
  the crops it makes cover the same person sizes as from the full-size photos (training shrinks
  these photos 0.25-0.9x anyway).

The pack is derived from licensed data: it goes to a git-ignored folder and must never be
committed (the data sets' terms forbid redistribution).
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

import cv2
import numpy as np
import scipy.io

from companion.evaluation import datasets as D
from companion.evaluation.compositor import layout_split

PACK_MANIFEST = "pack.json"


def _tree_bytes(root: Path) -> int:
    return sum(p.stat().st_size for p in root.rglob("*") if p.is_file())


def _write_shb_gt(path: Path, points: np.ndarray) -> None:
    """``GT_IMG_n.mat`` in ShanghaiTech's own nesting: ``image_info[0, 0][0, 0][0]`` is N x 2."""
    inner = np.zeros((1, 1), dtype=[("location", object), ("number", object)])
    inner[0, 0]["location"] = np.asarray(points, np.float64).reshape(-1, 2)
    inner[0, 0]["number"] = np.array([[len(points)]], np.float64)
    cell = np.empty((1, 1), dtype=object)
    cell[0, 0] = inner
    scipy.io.savemat(path, {"image_info": cell}, do_compression=True)


def pack(shared: Path, out: Path, shb_scale: float = 0.5, shb_quality: int = 75,
         layout_step: int = 10) -> dict[str, object]:
    """Write the pack; return its manifest (also written to ``out/pack.json``)."""
    if not 0 < shb_scale <= 1:
        raise ValueError(f"--shb-scale must be in (0, 1], got {shb_scale}")
    if not 1 <= shb_quality <= 100:
        raise ValueError(f"--shb-quality must be in 1-100, got {shb_quality}")
    if layout_step < 1:
        raise ValueError(f"--layout-step must be >= 1, got {layout_step}")
    src = Path(shared) / "data"
    dst = Path(out) / "data"
    if dst.exists():
        shutil.rmtree(dst)

    # Semantic drone: copied as is (its JPEGs are smaller than any re-encoding that keeps them).
    sd_src, sd_dst = src / "semantic_drone", dst / "semantic_drone"
    D.semantic_drone(shared, "train")  # a clear DatasetError when it is missing or malformed
    shutil.copytree(sd_src / "images", sd_dst / "images")
    shutil.copytree(sd_src / "labels", sd_dst / "labels")
    shutil.copy2(sd_src / "person_boxes.json", sd_dst / "person_boxes.json")

    # DroneCrowd: training frames, their sequence whole, the training layouts subsampled.
    dc_src, dc_dst = src / "dronecrowd", dst / "dronecrowd"
    (dc_dst / "gt").mkdir(parents=True)
    frame_seqs = {D.DRONECROWD_FRAMES[n][0] for n in D.DRONECROWD_TRAIN}
    for name in D.DRONECROWD_TRAIN:
        f = dc_src / "frames" / name[:6] / f"{name}.jpg"
        (dc_dst / "frames" / name[:6]).mkdir(parents=True, exist_ok=True)
        shutil.copy2(f, dc_dst / "frames" / name[:6] / f.name)
    n_layouts = 0
    for f in sorted((dc_src / "gt").glob("[0-9]*.mat")):
        if f.name in frame_seqs:
            shutil.copy2(f, dc_dst / "gt" / f.name)
        elif layout_split(int(f.stem)) == "train":
            anno = scipy.io.loadmat(f)["anno"]
            keep = anno[np.isin(anno[:, 0], np.unique(anno[:, 0])[::layout_step])]
            scipy.io.savemat(dc_dst / "gt" / f.name, {"anno": keep}, do_compression=True)
        else:
            continue
        n_layouts += 1

    # ShanghaiTech B training photos, downscaled.
    shb_dst = dst / "shanghaitech_b" / "train_data"
    (shb_dst / "images").mkdir(parents=True)
    (shb_dst / "ground-truth").mkdir(parents=True)
    samples = D.shanghaitech_b(shared, "train")
    for s in samples:
        img = s.image()
        h, w = img.shape[:2]
        small = cv2.resize(img, (round(w * shb_scale), round(h * shb_scale)), interpolation=cv2.INTER_AREA)
        fx, fy = small.shape[1] / w, small.shape[0] / h
        ok, buf = cv2.imencode(".jpg", small, [cv2.IMWRITE_JPEG_QUALITY, shb_quality])
        if not ok:
            raise D.DatasetError(f"cannot encode {s.path}")
        (shb_dst / "images" / f"{s.name}.jpg").write_bytes(buf.tobytes())
        _write_shb_gt(shb_dst / "ground-truth" / f"GT_{s.name}.mat", s.points * np.array([fx, fy], np.float32))

    manifest: dict[str, object] = {
        "from": str(Path(shared).resolve()),
        "shanghaitech_b": {"scale": shb_scale, "quality": shb_quality, "images": len(samples)},
        "dronecrowd": {"layout_step": layout_step, "sequences": n_layouts, "frames": list(D.DRONECROWD_TRAIN)},
        "semantic_drone": {"images": len(list((sd_dst / "images").glob("*.jpg")))},
    }
    (Path(out) / PACK_MANIFEST).write_text(json.dumps(manifest, indent=1) + "\n")
    return manifest


def shb_scale(shared: Path) -> float:
    """The factor ShanghaiTech B was downscaled by in a pack at ``shared`` (1.0 for ``../shared``)."""
    path = Path(shared) / PACK_MANIFEST
    if not path.is_file():
        return 1.0
    try:
        scale = float(json.loads(path.read_text())["shanghaitech_b"]["scale"])
    except (ValueError, KeyError, TypeError) as exc:
        raise D.DatasetError(f"{path} is not a training pack's manifest: {exc}") from None
    if not 0 < scale <= 1:
        raise D.DatasetError(f"{path}: shanghaitech_b.scale must be in (0, 1], got {scale}")
    return scale


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--shared", type=Path, default=Path("../shared"))
    p.add_argument("--out", type=Path, default=Path(".pack/shared"), help="pack folder (git-ignored)")
    p.add_argument("--shb-scale", type=float, default=0.5)
    p.add_argument("--shb-quality", type=int, default=75)
    p.add_argument("--layout-step", type=int, default=10)
    args = p.parse_args(argv)
    try:
        m = pack(args.shared, args.out, args.shb_scale, args.shb_quality, args.layout_step)
    except (ValueError, D.DatasetError) as exc:
        print(f"companion.training.pack: {exc}", file=sys.stderr)
        return 2
    print(f"{args.out}: {_tree_bytes(args.out) / 2**20:.1f} MiB ({json.dumps(m)})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
