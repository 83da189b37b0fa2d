"""`nrhdr batch` scaling: frames/s of the Dask driver with 1 and 2 local workers against the
same per-frame function in a plain loop in this process (the anchor, measured in the same run), the
scheduler's overhead per frame, the data moved per frame, and the projection for N machines.

    .venv/bin/python benchmarks/batch_scaling.py --quick      # 256 x 192, 12 frames, fse fast, ~2 min
    .venv/bin/python benchmarks/batch_scaling.py              # 640 x 480, 24 frames, fse fast
    .venv/bin/python benchmarks/batch_scaling.py --preset best --frames 8

Runs (each on the same simulated clip, outputs to a fresh temp folder, JIT/warm-up excluded):
  loop xT    chain.process_frame + io.write_exr in a plain loop here, numba with T threads (T = cores, 1)
  dask WxT   nrhdr_core.batch.run_dask on a LocalCluster of W worker processes, numba T threads each
  no-op      200 tasks that return at once, all in flight: the scheduler's cost per frame (its throughput
             bound), with the task's arguments as in --transfer files (a few hundred bytes) and as in
             --transfer data (+ the raw frame)
Writes bench_out/batch_scaling/results.json; prints a markdown table for docs/BENCHMARKS.md.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from nrhdr_core import batch, chain  # noqa: E402

OUT = ROOT / "bench_out" / "batch_scaling"


def make_clip(folder: Path, width: int, height: int, frames: int) -> Path:
    from nrhdr_core import profile, scene, simulate
    prof = profile.default(height, width, seed=0)
    sc = scene.synthetic_hdr_scene(height=max(2 * height, 240), width=max(2 * width, 320), seed=7)
    simulate.simulate_clip(sc, folder, prof, frames=frames, fps=30, progress=False)
    return folder


def job_for(clip: Path, out: Path, settings) -> batch.Job:
    return batch.Job(batch.open_source(clip), out, settings)


def _record(tag, workers, threads, res) -> dict:
    r = {"run": tag, "workers": workers, "threads": threads, "frames": len(res.done), "seconds": res.seconds,
         "fps": res.fps, "compute_s": res.frame_seconds, "cpu_s": res.frame_cpu_seconds,
         "failed": len(res.failures)}
    if workers:   # the workers' idle share: wall x workers against the summed compute time of the frames
        r["idle_worker_s_per_frame"] = (res.seconds * workers - res.frame_seconds) / max(len(res.done), 1)
    return r


def run_loop(clip, settings, threads: int, tmp: Path, tag: str) -> dict:
    import numba
    old = numba.get_num_threads()
    numba.set_num_threads(threads)
    try:
        shutil.rmtree(tmp / tag, ignore_errors=True)
        job = job_for(clip, tmp / tag, settings)
        todo, _ = batch.prepare_output(job)
        res = batch.run_loop(job, todo)
    finally:
        numba.set_num_threads(old)
    return _record(tag, 0, threads, res)


def run_dask(client, clip, settings, workers: int, threads: int, tmp: Path, tag: str, transfer="files",
             warm=True) -> dict:
    shutil.rmtree(tmp / tag, ignore_errors=True)
    job = job_for(clip, tmp / tag, settings)
    todo, _ = batch.prepare_output(job)
    res = batch.run_dask(job, todo, client, return_files=transfer == "data", warm=warm)
    return _record(tag, workers, threads, res)


def _noop(index, src, profile, xt, settings, files, raw=None, return_files=False, stage=None):
    return index, (0.0, 0.0), None


def noop_overhead(client, job, n: int) -> dict:
    """The scheduler's throughput bound: milliseconds per task when `n` tasks that do nothing are in
    flight at once, with the task arguments of --transfer files (a few hundred bytes) and --transfer data
    (+ the raw frame)."""
    from distributed import wait
    out = {}
    prof_f = client.scatter(job.profile, broadcast=True, hash=False)
    raw = batch.read_frame(job.source.raw, job.source.width, job.source.height, 0)
    for mode, r in (("files", None), ("data", raw)):
        t0 = time.perf_counter()
        futs = [client.submit(_noop, i, job.source, prof_f, None, job.settings, ["x"], r, False, pure=False)
                for i in range(n)]
        wait(futs)
        out[f"noop_ms_per_frame_{mode}"] = 1e3 * (time.perf_counter() - t0) / n
        client.cancel(futs)
        del futs
    return out


def projection(per_machine_fps: float, sched_ms: float, raw_bytes: int, exr_bytes: int,
               link_bytes_s: float = 125e6) -> list[dict]:
    """fps for N machines: N x one machine's rate, capped by the scheduler (1 / its cost per task) and,
    with --transfer data, by the client's network link (raw frame out + EXR back per frame)."""
    rows = []
    sched_cap = 1e3 / sched_ms if sched_ms > 0 else float("inf")
    link_cap = link_bytes_s / (raw_bytes + exr_bytes)
    for n in (1, 2, 4, 8, 16, 32, 64):
        ideal = n * per_machine_fps
        rows.append({"machines": n, "ideal_fps": ideal, "files_fps": min(ideal, sched_cap),
                     "data_fps": min(ideal, sched_cap, link_cap)})
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="256 x 192, 12 frames")
    ap.add_argument("--width", type=int, help="default 640 (--quick 256)")
    ap.add_argument("--height", type=int, help="default 480 (--quick 192)")
    ap.add_argument("--frames", type=int, help="default 24 (--quick 12)")
    ap.add_argument("--method", default="fse", choices=chain.METHODS)
    ap.add_argument("--preset", default="fast", choices=chain.PRESETS)
    ap.add_argument("--repeat", type=int, help="round-robin repetitions, the best counts (default 3, --quick 2)")
    a = ap.parse_args(argv)
    for k, full, quick in (("width", 640, 256), ("height", 480, 192), ("frames", 24, 12), ("repeat", 3, 2)):
        if getattr(a, k) is None:
            setattr(a, k, quick if a.quick else full)
    cores = batch.usable_cores()
    settings = chain.ChainSettings(method=a.method, preset=a.preset)
    OUT.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="nrhdr-batch-bench-") as td:
        tmp = Path(td)
        clip = make_clip(tmp / "clip", a.width, a.height, a.frames)
        batch.warm_cache(settings)
        # every configuration's cluster stays up; the runs go round-robin a.repeat times and the best
        # (least disturbed) of each counts: the machine may be shared
        configs = [(1, 1)] + ([(cores, 1), (1, cores)] if cores > 1 else [])
        runs = [("loop", 0, cores, "files"), ("loop", 0, 1, "files")]
        runs += [("dask", w, t, "files") for w, t in configs]
        if cores > 1:
            runs.append(("dask", cores, 1, "data"))
        all_rows: dict[str, list] = {}
        noop = {}
        with contextlib.ExitStack() as stack:
            clients = {(w, t): stack.enter_context(batch.local_client(w, t)) for w, t in configs}
            for rep in range(a.repeat):
                for kind, w, t, transfer in runs:
                    if kind == "loop":
                        tag = f"loop x{t}"
                        r = run_loop(clip, settings, t, tmp, tag)
                    else:
                        tag = f"dask {w}x{t}" + (" data" if transfer == "data" else "")
                        r = run_dask(clients[(w, t)], clip, settings, w, t, tmp, tag, transfer, warm=rep == 0)
                    all_rows.setdefault(tag, []).append(r)
            for (w, t), client in clients.items():
                job = job_for(clip, tmp / "noop", settings)
                noop[(w, t)] = noop_overhead(client, job, 200)
        rows = []
        for tag, rs in all_rows.items():
            best = dict(max(rs, key=lambda r: r["fps"]))
            best["fps_all"] = [r["fps"] for r in rs]
            if best["workers"]:
                best.update(noop[(best["workers"], best["threads"])])
            rows.append(best)
        exr = [f.stat().st_size for f in (tmp / f"loop x{cores}").glob("frame_*.exr")]
    exr_bytes = int(np.mean(exr))
    raw_bytes = 2 * a.width * a.height
    anchor = rows[0]["fps"]
    anchor1 = rows[1]["fps"]
    cpu1 = rows[1]["cpu_s"] / max(rows[1]["frames"], 1)   # CPU seconds per frame of the 1-thread loop
    spread = ", ".join(f"{r['run']}: " + "/".join(f"{f:.2f}" for f in r["fps_all"]) for r in rows)
    print(f"# nrhdr batch scaling: {a.width} x {a.height}, {a.frames} frames, {a.method} {a.preset}, "
          f"{cores} cores, {platform.processor() or platform.machine()}")
    print(f"anchor: loop x{cores} {anchor:.2f} frames/s, loop x1 {anchor1:.2f} frames/s; best of "
          f"{a.repeat} round-robin runs each (all: {spread})\n")
    print("| run | workers x numba threads | frames/s | vs loop x%d | efficiency vs %s x loop x1 | "
          "CPU ms/frame | CPU efficiency vs loop x1 | wall ms/frame in the task | idle worker ms/frame | "
          "no-op task ms (files / data) |"
          % (cores, "W"))
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        w = max(r["workers"], 1)
        wt = f"{r['workers']} x {r['threads']}" if r["workers"] else f"loop, {r['threads']} threads"
        eff = r["fps"] / (w * r["threads"] * anchor1) if anchor1 else 0.0
        idle = f"{1e3 * r['idle_worker_s_per_frame']:.1f}" if "idle_worker_s_per_frame" in r else "-"
        noop = (f"{r['noop_ms_per_frame_files']:.2f} / {r['noop_ms_per_frame_data']:.2f}"
                if "noop_ms_per_frame_files" in r else "-")
        n = max(r["frames"], 1)
        print(f"| {r['run']} | {wt} | {r['fps']:.2f} | {r['fps'] / anchor:.2f} | {eff:.2f} | "
              f"{1e3 * r['cpu_s'] / n:.0f} | {cpu1 / (r['cpu_s'] / n):.2f} | {1e3 * r['compute_s'] / n:.0f} | "
              f"{idle} | {noop} |")
    best = max((r for r in rows if r["workers"]), key=lambda r: r["fps"])
    sched_ms = best["noop_ms_per_frame_files"]
    print(f"\ndata per frame: raw in {raw_bytes / 1e3:.1f} kB, EXR (Y + state) out {exr_bytes / 1e3:.1f} kB "
          f"(values + state in memory: {5 * a.width * a.height / 1e3:.1f} kB)")
    proj = projection(best["fps"], sched_ms, raw_bytes, exr_bytes)
    print(f"\nprojection from '{best['run']}' ({best['fps']:.2f} frames/s per machine), scheduler "
          f"{sched_ms:.2f} ms per frame, 1 Gbit/s client link for --transfer data:\n")
    print("| machines | ideal frames/s | --transfer files | --transfer data |")
    print("|---|---|---|---|")
    for p in proj:
        print(f"| {p['machines']} | {p['ideal_fps']:.1f} | {p['files_fps']:.1f} | {p['data_fps']:.1f} |")
    doc = {"width": a.width, "height": a.height, "frames": a.frames, "method": a.method, "preset": a.preset,
           "cores": cores, "rows": rows, "raw_bytes": raw_bytes, "exr_bytes": exr_bytes, "projection": proj,
           "time": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
    (OUT / "results.json").write_text(json.dumps(doc, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
