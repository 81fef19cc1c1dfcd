"""``companion eval``: measure a density model (and optionally a peer) on the crowd data sets.

    companion eval                                   # the shipped model, every figure
    companion eval --peer ../shared/peers/mcnn-shb.onnx --mall-step 1 --json
    companion eval --model other.onnx --color gray --scale 1 --stride 4
    companion eval --model ../shared/peers/mcnn-shb.onnx --preset mcnn

Figures (definitions in :mod:`companion.evaluation.metrics`): ShanghaiTech B test MAE / RMSE;
Mall 801-2000 MAE; occupancy head recall and free-area share at the model's default threshold
(its ``companion.occupancy_threshold``, else the paper's 0) on the six DroneCrowd frames, the
held-out DroneCrowd frame ``img017012``, Mall 801-2000 and the held-out fifth of the semantic drone
photos, and on request (``--sets``) those photos downscaled x0.5 and x0.25 (``semantic-scaled``:
real pixels of smaller people) and the synthetic hold-out (``synthetic``); the recall/free curve over
thresholds; density latency at 640x480 and 1280x720.

Recall by person size, on the sets that give person sizes (semantic drone, also downscaled: its
person boxes; synthetic: the pasted silhouettes; the others have head points only): recall per size bin and
``min_person_px``, the smallest size from which recall reaches 99.5 % (``metrics.min_person_px``).
The model's figure is the largest over those sets (None if any never reaches it); the model's own
``companion.min_person_px`` metadata is printed beside it.
With ``--peer`` the second model is measured in the same run, its recall is also read off its
curve at our free share, and the latency ratio is printed.

The ``landability`` set measures the landability model (``--landability``, default the shipped
one) on the same held-out semantic-drone fifth: IoU per risk level and of the unlandable/landable
decision, per class the share of its pixels put in its own level and called unlandable, and the
share of each proposed landing circle's pixels that truly is landable ground (the whole pipeline,
people and landability, on each photo seen straight down at ``--gsd`` m/px); definitions in
:mod:`companion.evaluation.landability`.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any, TextIO

from companion.config import SHIPPED_LANDABILITY, SHIPPED_MODEL
from companion.evaluation import compositor as C
from companion.evaluation import datasets as D
from companion.evaluation.landability import SEMANTIC_GSD, LandabilityResult, evaluate_landability
from companion.evaluation.metrics import (
    SetResult,
    bench_frame,
    evaluate_set,
    latency_ms,
    latency_pair_ms,
    overall_min_person_px,
)
from companion.pipeline.density import DensityModel, DensityModelError, resolve_threshold
from companion.pipeline.landability import LandabilityModel
from companion.pipeline.occupancy import OccupancyParams

REPO = Path(__file__).resolve().parents[2]
PRESETS: dict[str, dict[str, object]] = {
    "none": {},
    # The MCNN peer: greyscale 0-255, no normalisation, stride 4 (shared/README.md).
    "mcnn": {"color": "gray", "scale": 1.0, "mean": 0.0, "std": 1.0, "stride": 4},
}
SETS = ("shb", "mall", "dronecrowd", "semantic", "semantic-scaled", "synthetic", "landability")
DEFAULT_SETS = ("shb", "mall", "dronecrowd", "semantic", "landability")
LATENCY_SIZES = {"640x480": (480, 640), "1280x720": (720, 1280)}


def _default_shared() -> Path:
    for cand in (Path.cwd() / "../shared", REPO.parent / "shared"):
        if (cand / "data").is_dir():
            return cand.resolve()
    return (Path.cwd() / "../shared").resolve()


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", type=Path, default=SHIPPED_MODEL, help="ONNX density model (default: the shipped one)")
    parser.add_argument("--preset", choices=sorted(PRESETS), default="none", help="settings of a known model family")
    g = parser.add_argument_group("overrides of the model's metadata")
    g.add_argument("--color", choices=["bgr", "rgb", "gray"])
    g.add_argument("--scale", type=float, help="multiplier on 0-255 pixel values")
    g.add_argument("--mean", help="comma-separated per-channel mean (after scale)")
    g.add_argument("--std", help="comma-separated per-channel std")
    g.add_argument("--stride", type=int, help="output stride")
    g.add_argument("--input-multiple", type=int, help="pad input to a multiple of N pixels")
    g.add_argument("--threshold", type=float, help="occupancy threshold (default: the model's, else 0)")
    g.add_argument("--count-scale", type=float, help="people per unit of map sum")
    parser.add_argument("--landability", type=Path, default=SHIPPED_LANDABILITY,
                        help="ONNX landability model for the landability set (default: the shipped one)")
    parser.add_argument("--gsd", type=float, default=SEMANTIC_GSD,
                        help=f"metres per pixel of the semantic-drone photos for the landability set's "
                             f"circles (default {SEMANTIC_GSD})")
    parser.add_argument("--peer", type=Path, help="a second model measured in the same run")
    parser.add_argument("--peer-preset", choices=sorted(PRESETS), help="default: mcnn if the file name says mcnn")
    parser.add_argument("--peer-threshold", type=float, help="occupancy threshold of the peer (default its own, else 0)")
    parser.add_argument("--shared", type=Path, default=None, help="shared data directory (default ../shared)")
    parser.add_argument("--sets", default=",".join(DEFAULT_SETS),
                        help=f"comma-separated subset of {','.join(SETS)} (default: {','.join(DEFAULT_SETS)})")
    parser.add_argument("--synthetic-n", type=int, default=200, help="synthetic hold-out images (512x512)")
    parser.add_argument("--synthetic-seed", type=int, default=13, help="seed of the synthetic hold-out")
    parser.add_argument("--mall-step", type=int, default=1, help="use every N-th Mall frame (default 1: all 1,200)")
    parser.add_argument("--limit", type=int, default=0, help="at most N images per set (0: all; for quick checks)")
    parser.add_argument("--threads", type=int, default=2, help="onnxruntime threads")
    parser.add_argument("--latency-runs", type=int, default=20, help="timed runs per size (0: skip latency)")
    parser.add_argument("--min-people", type=float, default=0.0,
                        help="occupied patches of the density map holding fewer people than this are specks, not "
                             "occupied (OccupancyParams.min_mass, a rule measured, not flown; default 0: every patch, "
                             "the paper's rule)")
    parser.add_argument("--curve", action="store_true", help="print the recall/free curves as well")
    parser.add_argument("--json", action="store_true", help="print one JSON document instead of text")


def _overrides(args: argparse.Namespace) -> dict[str, object]:
    ov = dict(PRESETS[args.preset])
    for key in ("color", "scale", "mean", "std", "stride", "input_multiple", "count_scale"):
        if getattr(args, key) is not None:
            ov[key] = getattr(args, key)
    if args.threshold is not None:
        ov["occupancy_threshold"] = args.threshold
    return ov


def _datasets(shared: Path, sets: list[str], mall_step: int, limit: int, synthetic_n: int = 200,
              synthetic_seed: int = 13) -> dict[str, list[D.Sample]]:
    out: dict[str, list[D.Sample]] = {}
    if "shb" in sets:
        out["shanghaitech_b_test"] = D.shanghaitech_b(shared, "test")
    if "dronecrowd" in sets:
        out["dronecrowd6"] = D.dronecrowd_frames(shared)
        out["dronecrowd_img017012"] = D.dronecrowd_frames(shared, ["img017012"])
    if "mall" in sets:
        out["mall"] = D.mall(shared, mall_step)
    if "semantic" in sets:
        out["semantic_drone_val"] = D.semantic_drone(shared, "val")
    if "semantic-scaled" in sets:
        val = D.semantic_drone(shared, "val")
        for f in D.SEMANTIC_SCALES:
            out[f"semantic_drone_val_x{f:g}"] = D.scaled(val, f, f"_x{f:g}")
    if "synthetic" in sets:
        if synthetic_n < 1:
            raise ValueError(f"--synthetic-n must be >= 1, got {synthetic_n}")
        out["synthetic_val"] = C.synthetic_set(shared, synthetic_n, synthetic_seed)
    if limit:
        out = {k: v[:limit] for k, v in out.items()}
    return out


def measure(model: DensityModel, data: dict[str, list[D.Sample]], latency_runs: int,
            min_people: float = 0.0) -> dict[str, Any]:
    """All figures of one model as a JSON-able dict; ``min_people``: occupied patches holding
    fewer people are specks (``OccupancyParams.min_mass``; the recall and free share at the
    threshold, not the curve)."""
    thr = resolve_threshold(None, model.spec)
    params = OccupancyParams(min_mass=min_people / model.spec.count_scale)
    sets: dict[str, SetResult] = {}
    for name, samples in data.items():
        counting = name in ("shanghaitech_b_test", "mall")
        sets[name] = evaluate_set(name, samples, model, thr, model.count if counting else None, params=params)
    out: dict[str, Any] = {
        "model": str(model.path),
        "min_people": min_people,
        "spec": {k: getattr(model.spec, k) for k in model.spec.__dataclass_fields__},
        "threshold": thr,
        "sets": {k: vars(v) for k, v in sets.items()},
        # Measured here: the largest per-set figure, None if a sized set never reaches 99.5 %.
        "min_person_px": overall_min_person_px(sets.values()),
        "min_person_px_sets": [k for k, r in sets.items() if r.size_recall is not None],
        "min_person_px_metadata": model.min_person_px,
    }
    if latency_runs > 0:
        src = next(iter(data.values()))[0].image()
        out["latency_ms"] = {k: latency_ms(model, bench_frame(src, hw), latency_runs) for k, hw in LATENCY_SIZES.items()}
    out["_results"] = sets
    return out


def _fmt(v: float | None, pct: bool = False) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "-"
    return f"{100 * v:.1f} %" if pct else f"{v:.2f}"


def _print(res: dict[str, Any], curve: bool, file: TextIO = sys.stdout) -> None:
    print(f"model {res['model']}  threshold {res['threshold']:.4g}  (count_scale {res['spec']['count_scale']:.4g})", file=file)
    for name, s in res["sets"].items():
        line = f"  {name:22s} images {s['images']:5d} heads {s['heads']:6d}  recall {_fmt(s['recall'], True):>8s}  free {_fmt(s['free'], True):>8s}"
        if s["mae"] is not None:
            line += f"  MAE {_fmt(s['mae'])}  RMSE {_fmt(s['rmse'])}"
        if "ours_recall_at_peer_free" in s:
            line += (f"  | at the peer's free {_fmt(s['peer_free'], True)}: ours {_fmt(s['ours_recall_at_peer_free'], True)}"
                     f" vs peer {_fmt(s['peer_recall'], True)}; peer at our free: {_fmt(s['peer_recall_at_our_free'], True)}"
                     f" (its best: {_fmt(s['peer_best_recall'], True)} at free {_fmt(s['peer_best_recall_free'], True)})")
        print(line, file=file)
        if s.get("size_recall") is not None:
            bins = "  ".join(f"{b['lo']:g}-{b['hi']:g} px: {_fmt(b['recall'], True)} ({b['people']})"
                             for b in s["size_recall"] if b["people"])
            mp = s["min_person_px"]
            print(f"      by person size: {bins}; recall >= 99.5 % from {'-' if mp is None else f'{mp:g} px'}", file=file)
        if curve:
            for c in s["curve"]:
                print(f"      t={c['threshold']:<10.4g} recall {_fmt(c['recall'], True):>8s} free {_fmt(c['free'], True):>8s}", file=file)
    mp, meta = res.get("min_person_px"), res.get("min_person_px_metadata")
    print(f"  min_person_px measured {'not reached' if mp is None else f'{mp:g} px'} on "
          f"{', '.join(res.get('min_person_px_sets') or ['no set with person sizes'])}; "
          f"model metadata {'none' if meta is None else f'{meta:g} px'}", file=file)
    for k, v in res.get("latency_ms", {}).items():
        print(f"  latency {k:9s} median {v['median']:.1f} ms (p10 {v['p10']:.1f}, p90 {v['p90']:.1f}, {v['runs']} runs)", file=file)


def run(args: argparse.Namespace) -> int:
    shared = args.shared or _default_shared()
    sets = [s.strip() for s in args.sets.split(",") if s.strip()]
    bad = sorted(set(sets) - set(SETS))
    if bad:
        print(f"companion eval: unknown set(s) {', '.join(bad)}; known: {', '.join(SETS)}", file=sys.stderr)
        return 2
    if not (math.isfinite(args.min_people) and args.min_people >= 0):
        print(f"companion eval: --min-people must be a finite number >= 0, not {args.min_people}", file=sys.stderr)
        return 2
    try:
        model = DensityModel(args.model, threads=args.threads, overrides=_overrides(args))
        peer = None
        if args.peer:
            preset = args.peer_preset or ("mcnn" if "mcnn" in args.peer.name.lower() else "none")
            pov = dict(PRESETS[preset])
            if args.peer_threshold is not None:
                pov["occupancy_threshold"] = args.peer_threshold
            peer = DensityModel(args.peer, threads=args.threads, overrides=pov)
        data = _datasets(Path(shared), sets, args.mall_step, args.limit, args.synthetic_n, args.synthetic_seed)
        land = None
        if "landability" in sets:
            land = (LandabilityModel(args.landability, threads=args.threads),
                    D.semantic_drone(Path(shared), "val")[: args.limit or None], D.semantic_classes(Path(shared)))
    except (DensityModelError, D.DatasetError, ValueError) as exc:
        print(f"companion eval: {exc}", file=sys.stderr)
        return 2
    land_res = None
    if land is not None:
        try:
            land_res = evaluate_landability(land[1], land[0], land[2], density=model, gsd=args.gsd)
        except ValueError as exc:  # a grouping naming classes the data set lacks
            print(f"companion eval: {args.landability}: {exc}", file=sys.stderr)
            return 2
    if not data and land_res is not None:  # only the landability set asked for
        doc0: dict[str, Any] = {"shared": str(shared), "landability": _land_doc(land_res, args.landability)}
        if args.json:
            json.dump(doc0, sys.stdout, indent=1)
            print()
        else:
            print(f"shared {shared}")
            _print_land(doc0["landability"])
        return 0
    # With a peer, latency is timed alternately below (fair ratio on a shared machine).
    res = measure(model, data, 0 if args.peer else args.latency_runs, args.min_people)
    doc: dict[str, Any] = {"shared": str(shared), "mall_step": args.mall_step, "limit": args.limit, "model": res}
    if peer is not None:
        pres = measure(peer, data, 0)
        doc["peer"] = pres
        for name, ours in res["_results"].items():
            theirs = pres["_results"][name]
            best, best_free = theirs.best_recall()
            res["sets"][name].update(
                peer_recall_at_our_free=theirs.at_free(ours.free),
                peer_best_recall=best,
                peer_best_recall_free=best_free,
                peer_free=theirs.free,
                peer_recall=theirs.recall,
                ours_recall_at_peer_free=ours.at_free(theirs.free),
            )
        if args.latency_runs > 0:
            src = next(iter(data.values()))[0].image()
            res["latency_ms"], pres["latency_ms"] = {}, {}
            for k, hw in LATENCY_SIZES.items():
                res["latency_ms"][k], pres["latency_ms"][k] = latency_pair_ms([model, peer], bench_frame(src, hw), args.latency_runs)
            doc["latency_ratio_ours_over_peer"] = {
                k: res["latency_ms"][k]["median"] / pres["latency_ms"][k]["median"] for k in LATENCY_SIZES
            }
        pres.pop("_results")
    res.pop("_results")
    if land_res is not None:
        doc["landability"] = _land_doc(land_res, args.landability)
    if args.json:
        json.dump(doc, sys.stdout, indent=1)
        print()
    else:
        print(f"shared {shared}  mall step {args.mall_step}" + (f"  limit {args.limit}" if args.limit else ""))
        _print(res, args.curve)
        if peer is not None:
            print("peer:")
            _print(doc["peer"], args.curve)
            for k, v in doc.get("latency_ratio_ours_over_peer", {}).items():
                print(f"  latency ratio ours/peer at {k}: {v:.2f}")
        if "landability" in doc:
            _print_land(doc["landability"])
    return 0


def _land_doc(res: LandabilityResult | None, path: Path) -> dict[str, Any]:
    d = dict(vars(res)) if res is not None else {}
    d["model"] = str(path)
    return d


def _print_land(d: dict[str, Any], file: TextIO = sys.stdout) -> None:
    print(f"landability {d['model']} on semantic_drone_val ({d['images']} photos), threshold {d['threshold']:.3g}",
          file=file)
    print("  IoU per level: " + "  ".join(f"{k} {_fmt(v, True)}" for k, v in d["level_iou"].items())
          + f"  | mean {_fmt(d['mean_iou'], True)}, pixel accuracy {_fmt(d['pixel_accuracy'], True)}", file=file)
    print(f"  decision at the threshold: unlandable IoU {_fmt(d['unlandable_iou'], True)}, "
          f"landable IoU {_fmt(d['landable_iou'], True)}", file=file)
    print("  per class (pixels in its own level / called unlandable): " + "  ".join(
        f"{k} {_fmt(d['class_in_level'][k], True)}/{_fmt(d['class_unlandable'][k], True)}"
        for k in d["class_in_level"]), file=file)
    print(f"  circles: {d['circles']} on {d['images_with_circles']} photos (gsd {d['gsd']:g} m/px); truly landable "
          f"pixels inside them: pooled {_fmt(d['circle_landable_pooled'], True)}, median "
          f"{_fmt(d['circle_landable_median'], True)}, worst {_fmt(d['circle_landable_min'], True)}; "
          f"circles >= 99 % landable: {_fmt(d['circles_at_least_99'], True)}", file=file)
