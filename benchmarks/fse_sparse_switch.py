"""`fast` preset: the sparse switch (32 x 32 window below `sparse_below` known) at 40 % against 30 %, on
1080p Desk frames near 40 % known (log2 PSNR of the reconstructed pixels against the truth) and Kodak at
35 / 38 % known (docs/FSE.md "Presets"). Needs a calibrated 1080p profile and a Desk clip:

    nrhdr simulate-flats flats --width 1920 --height 1080 --sensor-model prototype --exposures 24 --frames 2
    nrhdr calibrate flats --mask flats/mask.png -o cal/cam.json
    nrhdr simulate ../shared/data/hdr/Desk.exr -o desk --frames 8 --profile cal/cam.json --sensor-model prototype
    python benchmarks/fse_sparse_switch.py cal/cam.json desk ../shared/data/kodak
"""
import sys
import time
from pathlib import Path

import numpy as np
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from nrhdr_core import crosstalk, io, metrics, profile, validity  # noqa: E402
from nrhdr_core import reconstruction as R  # noqa: E402

cal, clip, kodak = (sys.argv[1:4] + [None] * 3)[:3] if len(sys.argv) > 3 else ("cal/cam.json", "desk",
                                                                                "../shared/data/kodak")
prof = profile.load(cal)
crosstalk.compact_for(prof)
raws = np.fromfile(f"{clip}/clip.raw", dtype="<u2").reshape(-1, prof.height, prof.width)
for i in range(4):
    v, s = validity.classify(raws[i].copy(), prof, dark_policy="weighted"); crosstalk.correct(v, s, prof, mode="lut", lut="compact")
    t, _ = io.read_exr(f"{clip}/truth/frame_{i:05d}.exr")
    miss = validity.missing_mask(s)
    row = [f"frame {i} known {validity.known_mask(s).mean():.3f}"]
    for sb in (0.4, 0.3):
        vv, ss = v.copy(), s.copy()
        t0 = time.perf_counter()
        R.reconstruct_frame(vv, ss, method="fse", preset="fast", noise=prof, sparse_below=sb)
        dt = time.perf_counter() - t0
        lp = metrics.log2_psnr(np.minimum(t, prof.white)[miss], np.minimum(vv, prof.white)[miss], 1.0, float(np.log2(prof.white)))
        row.append(f"sparse_below {sb}: {lp:.3f} dB {dt*1e3:.0f} ms")
    print(" | ".join(row))
rng = np.random.default_rng(0)
for name in ("kodim01", "kodim03", "kodim05"):
    img = np.asarray(Image.open(f"{kodak}/{name}.png").convert('L'), np.float32)
    for share in (0.35, 0.38):
        k = rng.random(img.shape) < share
        r = []
        for sb in (0.4, 0.3):
            t0 = time.perf_counter()
            o = R.reconstruct(img, k, method="fse", preset="fast", sparse_below=sb)
            r.append(f"{sb}: {metrics.psnr(img, np.clip(o, 0, 255), 255):.3f} dB {1e3*(time.perf_counter()-t0):.0f} ms")
        print(name, share, " | ".join(r))
