"""Scratch planes reused frame after frame, also under gst-launch-1.0 (no per-frame allocation).
`threading.local()` loses its values whenever GStreamer's Python bindings drop the thread state after a
callback; nrhdr_core.scratch keys them by the OS thread instead (`ThreadScratch`, behind `planes`)."""
from __future__ import annotations

import resource
import subprocess
import threading

import numpy as np
import pytest

from nrhdr_core.scratch import ThreadScratch, planes

from conftest import make_test_clip


def test_values_are_private_to_their_thread():
    s = ThreadScratch()
    s.a = 1
    seen = {}

    def other():
        seen["before"] = getattr(s, "a", None)
        s.a = 2
        seen["after"] = s.a

    t = threading.Thread(target=other)
    t.start()
    t.join()
    assert seen == {"before": None, "after": 2}
    assert s.a == 1
    with pytest.raises(AttributeError):
        _ = s.missing


def test_exited_threads_are_dropped():
    s = ThreadScratch()
    s.a = 0

    def store(i):
        s.a = i

    for i in range(5):
        t = threading.Thread(target=store, args=(i,))
        t.start()
        t.join()
    # each new thread prunes the exited ones before it stores: this thread and the last one are left (and
    # the one before, if the kernel had not yet reaped it when the next one started); without pruning, 6
    assert s.threads() <= 3
    store(9)
    assert s.a == 9


def test_planes_are_kept_per_key_and_remade_when_it_changes():
    made = []

    def make(shape):
        made.append(shape)
        return np.zeros(shape, np.float32)
    a = planes("test_scratch.a", (3, 4), lambda: make((3, 4)))
    a[0, 0] = 7.0
    b = planes("test_scratch.a", (3, 4), lambda: make((3, 4)))
    assert b is a and b[0, 0] == 7.0 and made == [(3, 4)]
    c = planes("test_scratch.a", (5, 4), lambda: make((5, 4)))         # another key: made again
    assert c.shape == (5, 4) and made == [(3, 4), (5, 4)]
    d = planes("test_scratch.b", (5, 4), lambda: make((5, 4)))         # another name: its own planes
    assert d is not c and len(made) == 3


def test_planes_are_private_to_their_thread():
    mine = planes("test_scratch.t", (2, 2), lambda: np.zeros((2, 2), np.float32))
    seen = {}

    def other():
        seen["plane"] = planes("test_scratch.t", (2, 2), lambda: np.ones((2, 2), np.float32))
        seen["again"] = planes("test_scratch.t", (2, 2), lambda: np.ones((2, 2), np.float32))

    t = threading.Thread(target=other)
    t.start()
    t.join()
    assert seen["plane"] is not mine and seen["again"] is seen["plane"] and seen["plane"][0, 0] == 1.0
    assert planes("test_scratch.t", (2, 2), lambda: None) is mine


@pytest.mark.gst
@pytest.mark.parametrize("method,width,height", [("preview", 640, 480), ("fse", 320, 240)])
def test_gst_launch_does_not_fault_fresh_pages_every_frame(gst_subprocess_env, tmp_path, method, width, height):
    """Minor page faults of gst-launch-1.0 runs over 8 and 40 frames: the 32 extra frames must reuse the
    scratch planes, not touch fresh memory. Planes allocated per frame would cost 1,527 (preview, 640x480)
    and 513 (fse, 320x240) faults per extra frame, i.e. 5 and 7 float32 planes; reused, 12-22 (filesrc's
    fresh read buffers among them), under a third of a plane."""
    d, prof, _ = make_test_clip(tmp_path / "clip", width=width, height=height, frames=40, fps=30)

    def faults(n):
        before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_minflt
        p = subprocess.run(
            ["gst-launch-1.0", "-q", "filesrc", f"location={d / 'clip.raw'}", f"num-buffers={n}",
             f"blocksize={2 * width * height}", "!", "rawvideoparse", "format=gray16-le", f"width={width}",
             f"height={height}", "framerate=30/1", f"plane-strides=<{2 * width}>", "!",
             "nrvalidity", f"profile={d / 'camera.json'}", "!", "nrcrosstalk", "!",
             "nrreconstruct", f"method={method}", "!", "nrtonemap", "!", "fakesink"],
            env=gst_subprocess_env, capture_output=True, text=True, timeout=300)
        assert p.returncode == 0, p.stdout + p.stderr
        return resource.getrusage(resource.RUSAGE_CHILDREN).ru_minflt - before

    faults(2)                     # numba's cache loaded once, as a pipeline after `nrhdr warmup` finds it
    per_frame = (faults(40) - faults(8)) / 32.0
    plane_pages = width * height * 4 / resource.getpagesize()
    assert per_frame < plane_pages, (per_frame, plane_pages)
