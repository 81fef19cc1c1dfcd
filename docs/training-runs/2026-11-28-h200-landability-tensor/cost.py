# The cost rows of LANDABILITY_CARD.md (2026-11-28): the density model, MCNN and landability models timed
# alternately, 40 runs each, 2 onnxruntime threads. python docs/training-runs/.../cost.py MODEL.onnx ...
import sys, numpy as np, cv2
from pathlib import Path
from companion.pipeline.density import DensityModel
from companion.pipeline.landability import LandabilityModel
from companion.evaluation.metrics import latency_pair_ms, bench_frame
from companion.evaluation import datasets as D
src = D.semantic_drone(Path('../shared'), 'val')[0].image()
dens = DensityModel(Path('companion/models/slz-density.onnx'), threads=2)
from companion.evaluation.cli import PRESETS
peer = DensityModel(Path("../shared/peers/mcnn-shb.onnx"), threads=2, overrides=dict(PRESETS["mcnn"]))
names = sys.argv[1:]
lands = [LandabilityModel(Path(p), threads=2) for p in names]
for hw in ((480, 640), (720, 1280)):
    res = latency_pair_ms([dens, peer] + lands, bench_frame(src, hw), 40)
    d, m = res[0]['median'], res[1]['median']
    print(hw, f"density {d:.1f} ms, MCNN {m:.1f} ms, density/MCNN {d/m:.3f}")
    for n, r in zip(names, res[2:]):
        print(f"   {Path(n).name}: {r['median']:.1f} ms (p10 {r['p10']:.1f}), (density+it)/MCNN {(d + r['median'])/m:.3f}")
