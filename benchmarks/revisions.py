"""Two revisions of nrhdr side by side: the chain's outputs bit for bit and its speed per frame, measured in
the same run (alternating rounds, so load affects both alike). The check for a refactor that must not change
behaviour: `identical` and per-setting times within noise.

    .venv/bin/python benchmarks/revisions.py BASE_REV                 # BASE_REV against the working tree
    .venv/bin/python benchmarks/revisions.py BASE_REV HEAD_REV --rounds 5 --width 1920 --height 1080

Each revision other than the working tree is checked out once into bench_out/revisions/<sha> (a detached git
worktree, kept so its numba cache stays warm; `git worktree prune` after deleting the folder). Every
revision runs the same script in its own interpreter with only its own tree on the path:

- outputs: the synthesised scene at 256 x 192 through `chain.process_frame` for every reconstruction method and
  preset, both dark policies, crosstalk off / LUT compact / LUT full / kernel (identity calibration), plus
  the log tone map and PQ encoding: one SHA-256 over every value and state byte;
- speed: `chain.process_frame` at --width x --height for the settings of the live preview and of recording
  (`preview`, `fse fast`, with the LUT crosstalk), median milliseconds per frame over --frames frames, and
  each stage of it (validity, crosstalk, reconstruction) timed alone on the same frames.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

CHILD = r'''
import hashlib, json, sys, time
import numpy as np
from nrhdr_core import chain, crosstalk, profile, scene, sensor, simulate, tonemap

def frames(h, w, n, seed):
    mask = np.random.default_rng(seed).random((h, w)) < 0.5
    prof = profile.make(mask)
    cal = prof.replace(crosstalk=crosstalk.identity_calibration(mask, nd=prof.nd, black_level=prof.black_level,
                                                               clip_code=prof.clip_code))
    sc = scene.synthetic_hdr_scene(max(h, 240) + 40, max(w, 320) + 40, seed=7)
    k = simulate.exposure_scale(sc, prof, 0.0)
    rng = np.random.default_rng(seed)
    raws = [sensor.capture(simulate.view(sc, h, w, 0.2 + 0.6 * i / max(n - 1, 1), simulate.Motion())
                           * np.float32(k), prof, rng) for i in range(n)]
    return prof, cal, raws

mode, h, w, n = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
if mode == "outputs":
    prof, cal, raws = frames(192, 256, 2, 1)
    digest = hashlib.sha256()
    settings = [dict(method=m, preset=p, dark_policy=d, crosstalk="off")
                for m, p in (("fse", "preview"), ("fse", "fast"), ("fse", "balanced"), ("preview", "fast"),
                             ("linear", "fast"), ("nearest", "fast")) for d in ("weighted", "threshold")]
    settings += [dict(method=m, preset="fast", crosstalk=x, crosstalk_lut=l)
                 for m in ("fse", "preview") for x, l in (("lut", "compact"), ("lut", "full"), ("kernel", "compact"))]
    for raw in raws:
        for s in settings:
            st = chain.ChainSettings(**s)
            v, state = chain.process_frame(raw.copy(), cal if st.crosstalk != "off" else prof, st)
            digest.update(v.tobytes()); digest.update(state.tobytes())
        digest.update(chain.tonemap_frame(v, prof, st).tobytes())
        digest.update(tonemap.hdr_encode(v, float(prof.white) / prof.nd, "pq").tobytes())
    print(json.dumps({"sha256": digest.hexdigest(), "settings": len(settings)}))
else:
    prof, cal, raws = frames(h, w, n, 2)
    out = {}
    from nrhdr_core import crosstalk as xt, reconstruction as rc, validity as vd

    def stages(raw, st):      # chain.process_frame's calls, timed one by one
        t0 = time.perf_counter()
        v, s = vd.classify(raw, cal, mode=st.mode, l_min=st.l_min, dark_policy=st.dark_policy)
        t1 = time.perf_counter()
        v2, s2 = xt.correct(v, s, cal, st.crosstalk, lut=st.crosstalk_lut)
        t2 = time.perf_counter()
        rc.reconstruct_frame(v2, s2, method=st.method, preset=st.preset, use_bounds=st.use_bounds, noise=cal,
                             fusion=st.noise_fusion)
        t3 = time.perf_counter()
        return t1 - t0, t2 - t1, t3 - t2

    for name, s in (("preview, lut compact", dict(method="preview", crosstalk="lut")),
                    ("fse fast, lut compact", dict(method="fse", preset="fast", crosstalk="lut"))):
        st = chain.ChainSettings(**s)
        chain.process_frame(raws[0].copy(), cal, st)                       # compile / load the cache
        stages(raws[0].copy(), st)
        ts, parts = [], []
        for raw in raws:
            r = raw.copy()
            t = time.perf_counter()
            chain.process_frame(r, cal, st)
            ts.append(time.perf_counter() - t)
            parts.append(stages(raw.copy(), st))
        out[name] = 1e3 * sorted(ts)[len(ts) // 2]
        for j, stage in enumerate(("validity", "crosstalk", "reconstruction")):
            if name.startswith("fse") and stage != "reconstruction":
                continue                                                   # the same stages as preview's
            out[f"  {stage} ({name.split(',')[0]})"] = 1e3 * sorted(p[j] for p in parts)[len(parts) // 2]
    print(json.dumps(out))
'''


def _git(*args, cwd=ROOT) -> str:
    return subprocess.run(["git", *args], cwd=cwd, check=True, capture_output=True, text=True).stdout.strip()


def checkout(rev: str | None) -> tuple[str, Path]:
    """(label, tree) of a revision; None is the working tree."""
    if rev is None:
        return "working tree", ROOT
    sha = _git("rev-parse", "--verify", f"{rev}^{{commit}}")
    tree = ROOT / "bench_out" / "revisions" / sha[:12]
    if not (tree / "nrhdr_core").is_dir():
        tree.parent.mkdir(parents=True, exist_ok=True)
        _git("worktree", "add", "--detach", str(tree), sha)
    return f"{rev} ({sha[:9]})", tree


def run_child(tree: Path, mode: str, h: int, w: int, n: int) -> dict:
    env = dict(os.environ, PYTHONPATH=str(tree))
    r = subprocess.run([sys.executable, "-c", CHILD, mode, str(h), str(w), str(n)], cwd=tree, env=env,
                       capture_output=True, text=True)
    if r.returncode != 0:
        raise SystemExit(f"revisions: {tree}: the {mode} run failed:\n{r.stderr[-3000:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("base", help="the revision to compare against (a commit, branch or tag)")
    ap.add_argument("head", nargs="?", default=None, help="the other revision (default: the working tree)")
    ap.add_argument("--width", type=int, default=1920)
    ap.add_argument("--height", type=int, default=1080)
    ap.add_argument("--frames", type=int, default=9, help="frames timed per setting and round")
    ap.add_argument("--rounds", type=int, default=3, help="alternating rounds (base, head, base, head, ...)")
    a = ap.parse_args(argv)
    if not (a.width >= 16 and a.height >= 16 and a.frames >= 1 and a.rounds >= 1):
        ap.error("--width/--height must be >= 16, --frames and --rounds >= 1")
    revs = [checkout(a.base), checkout(a.head)]

    outs = [run_child(tree, "outputs", 0, 0, 0) for _, tree in revs]
    same = outs[0]["sha256"] == outs[1]["sha256"]
    print(f"outputs ({outs[0]['settings']} settings x 2 frames, tone map, PQ): "
          f"{'identical' if same else 'DIFFERENT'}")
    for (label, _), o in zip(revs, outs):
        print(f"  {label:32s} sha256 {o['sha256'][:16]}")

    times: list[dict[str, list[float]]] = [{}, {}]
    for _ in range(a.rounds):
        for i, (_, tree) in enumerate(revs):
            for k, v in run_child(tree, "speed", a.height, a.width, a.frames).items():
                times[i].setdefault(k, []).append(v)
    print(f"\nms per frame, chain.process_frame at {a.width} x {a.height} (median of {a.frames} frames; "
          f"each round's median, {a.rounds} alternating rounds)")
    print(f"{'setting':30s} | {revs[0][0]:>32s} | {revs[1][0]:>32s} | head / base")
    for k in times[0]:
        b, h = times[0][k], times[1][k]
        print(f"{k:30s} | {' '.join(f'{x:6.1f}' for x in b):>32s} | {' '.join(f'{x:6.1f}' for x in h):>32s} | "
              f"{statistics.median(h) / statistics.median(b):.3f}")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
