"""Sensor data formats of the camera profile (docs/PROFILE.md "Sensor data"): bit depth, white and black level,
LSB/MSB alignment, packed Mono12Packed / Mono12p / Mono10p frames, out-of-range codes; checked against
bit-by-bit references written here from the GenICam PFNC and GigE Vision definitions."""
from __future__ import annotations

import json

import numpy as np
import pytest

from nrhdr_core import profile, sensor, validity as V


def pack_bitstream(codes: np.ndarray, bits: int) -> np.ndarray:
    """PFNC Mono10p / Mono12p: every pixel's bits, LSB first, one after the other; no line padding."""
    stream = []
    for c in codes.reshape(-1).tolist():
        stream += [(c >> b) & 1 for b in range(bits)]
    stream += [0] * (-len(stream) % 8)
    return np.array([sum(stream[i + b] << b for b in range(8)) for i in range(0, len(stream), 8)], np.uint8)


def pack_mono12packed(codes: np.ndarray) -> np.ndarray:
    """GigE Vision Mono12Packed: per pixel pair, p0 bits 11..4, then p0 3..0 | p1 3..0 << 4, then p1 11..4."""
    c = codes.reshape(-1).astype(np.int64).tolist()
    if len(c) % 2:
        c.append(0)
    out = []
    for p0, p1 in zip(c[0::2], c[1::2]):
        out += [p0 >> 4, (p0 & 0xF) | ((p1 & 0xF) << 4), p1 >> 4]
    return np.array(out[:(len(codes.reshape(-1)) * 12 + 7) // 8], np.uint8)


PACKERS = {"mono12packed": (12, pack_mono12packed), "mono12p": (12, lambda c: pack_bitstream(c, 12)),
           "mono10p": (10, lambda c: pack_bitstream(c, 10))}


@pytest.mark.parametrize("packing", sorted(PACKERS))
@pytest.mark.parametrize("shape", [(6, 8), (5, 7)])      # an odd pixel count ends mid-byte
def test_packed_frames_unpack_to_their_codes(packing, shape):
    bits, pack = PACKERS[packing]
    rng = np.random.default_rng(hash((packing, shape)) % 2**32)
    codes = rng.integers(0, 1 << bits, shape).astype(np.uint16)
    codes.flat[:2] = [(1 << bits) - 1, 0]
    base = profile.default(*shape, seed=1)
    p = profile.make(base.mask, bit_depth=bits, packing=packing, white_level=(1 << bits) - 1,
                     gain=0.55 * (1 << bits) / 4096)
    data = pack(codes)
    assert p.frame_bytes() == data.size == (shape[0] * shape[1] * bits + 7) // 8
    assert np.array_equal(V.codes(data, p), codes)
    # classify on the packed bytes = classify on the codes with the unpacked profile
    plain = p.replace(packing="none")
    v, s = V.classify(data, p)
    v2, s2 = V.classify(codes, plain)
    assert np.array_equal(v, v2) and np.array_equal(s, s2)


def test_packed_buffer_of_the_wrong_size_is_an_error():
    base = profile.default(6, 8, seed=1)
    p = profile.make(base.mask, bit_depth=12, packing="mono12packed")
    with pytest.raises(V.FrameError, match=r"mono12packed.*72 bytes, got 96 bytes.*unpacked 16-bit"):
        V.codes(np.zeros(96, np.uint8), p)            # 2 bytes per pixel: not packed data
    with pytest.raises(V.FrameError, match=r"72 bytes, got 71 bytes"):
        V.classify(np.zeros(71, np.uint8), p)


def test_msb_aligned_codes_are_shifted_down():
    base = profile.default(8, 10, seed=4)
    p = profile.make(base.mask, bit_depth=12, alignment="msb")
    codes = np.random.default_rng(0).integers(0, 4096, (8, 10)).astype(np.uint16)
    words = (codes << 4) | 0x5                        # low bits hold anything
    assert np.array_equal(V.codes(words, p), codes)
    v, s = V.classify(words, p)
    v2, s2 = V.classify(codes, base)
    assert np.array_equal(v, v2) and np.array_equal(s, s2)
    # 8-bit frames widened by videoconvert (code * 257) read back exactly with bit_depth 8, msb
    p8 = profile.make(base.mask, bit_depth=8, alignment="msb", white_level=255, gain=0.05)
    c8 = np.arange(80, dtype=np.uint16).reshape(8, 10) * 3
    assert np.array_equal(V.codes(c8 * 257, p8), c8)


def test_white_level_sets_the_clip_code_and_black_level_is_subtracted():
    base = profile.default(4, 4, seed=2)
    p = profile.make(base.mask, bit_depth=16, white_level=60000, black_level=1000.0, gain=10.0, l_min=50.0)
    assert p.clip_code == 59999 and p.white == pytest.approx((59999 - 1000) * p.nd)
    raw = np.full((4, 4), 30000, np.uint16)
    raw[0, 0], raw[0, 1] = 59999, 59998
    v, s = V.classify(raw, p)
    assert s[0, 0] & V.REASON_MASK == V.CLIPPED and s[0, 1] & V.REASON_MASK != V.CLIPPED
    scale = np.where(p.mask, p.nd, 1.0)
    ok = (s & V.REASON_MASK) == V.VALID
    assert np.allclose(v[ok], ((raw.astype(np.float64) - 1000.0) * scale)[ok])
    # the noise model works on the signal above black: the SNR 0 dB level does not move with the black level
    assert sensor.zero_db_signal_dn(p) == pytest.approx(sensor.zero_db_signal_dn(p.replace(black_level=0.0)))
    # both given: kept; clip above white refused
    q = profile.make(base.mask, white_level=4000, clip_code=3990)
    assert (q.white_level, q.clip_code) == (4000, 3990)
    with pytest.raises(profile.ProfileError, match="clip_code.*white_level"):
        profile.make(base.mask, white_level=4000, clip_code=4001)
    with pytest.raises(profile.ProfileError, match="white_level.*1..4095"):
        profile.make(base.mask, white_level=5000)


def test_codes_beyond_the_bit_depth_are_an_error_when_the_profile_says_so():
    base = profile.default(4, 6, seed=2)
    ramp = np.linspace(0, 65535, 24).astype(np.uint16).reshape(4, 6)     # a full 16-bit ramp
    v, s = V.classify(ramp, base)                                         # out_of_range "clip": clipped
    assert ((s & V.REASON_MASK) == V.CLIPPED).sum() > 12
    strict = base.replace(out_of_range="error")
    with pytest.raises(V.FrameError, match=r"codes above the 12-bit range.*largest 65535.*bit_depth"):
        V.classify(ramp, strict)
    ok = np.minimum(ramp, 4095)
    V.classify(ok, strict)
    p16 = profile.make(base.mask, bit_depth=16, white_level=65535, gain=10.0, out_of_range="error")
    v, s = V.classify(ramp, p16)
    assert ((s & V.REASON_MASK) == V.CLIPPED).sum() == 1                  # only 65535


@pytest.mark.parametrize("fields,words", [
    ({"alignment": "middle"}, "alignment.*lsb, msb"),
    ({"packing": "mono14p"}, "packing.*mono12packed"),
    ({"packing": "mono12p"}, "packing.*12-bit codes but bit_depth is 16"),
    ({"packing": "mono10p", "bit_depth": 10, "alignment": "msb"}, "alignment.*must be 'lsb'"),
    ({"out_of_range": "wrap"}, "out_of_range.*clip, error"),
])
def test_format_fields_are_checked(fields, words):
    base = profile.default(4, 4, seed=2)
    fields = {"bit_depth": 16, "white_level": 65535, "gain": 10.0, **fields}
    if fields["bit_depth"] != 16:
        fields.update(white_level=(1 << fields["bit_depth"]) - 1, gain=1.0)
    with pytest.raises(profile.ProfileError, match=words):
        profile.make(base.mask, **fields)


def test_format_fields_roundtrip_and_version_rules(tmp_path):
    base = profile.default(6, 8, seed=3)
    p = profile.make(base.mask, bit_depth=12, packing="mono12p", white_level=4000, black_level=64.0,
                     out_of_range="error")
    doc = json.loads(profile.save(p, tmp_path / "cam.json").read_text())
    assert doc["version"] == 2 and doc["packing"] == "mono12p" and doc["white_level"] == 4000
    q = profile.load(tmp_path / "cam.json")
    for f in ("bit_depth", "packing", "white_level", "clip_code", "black_level", "alignment", "out_of_range"):
        assert getattr(q, f) == getattr(p, f), f
    # a version-1 file means what it always meant: its clip code, white = clip code + 1, LSB, unpacked
    doc1 = json.loads(profile.save(base, tmp_path / "old.json").read_text())
    assert doc1["version"] == 1 and not set(profile.V2_FIELDS) & set(doc1)
    o = profile.load(tmp_path / "old.json")
    assert (o.clip_code, o.white_level, o.alignment, o.packing, o.out_of_range) == (4094, 4095, "lsb", "none",
                                                                                    "clip")
    # a version-1 file with a version-2 field is refused: an older reader would misread the data
    (tmp_path / "mixed.json").write_text(json.dumps(dict(doc1, packing="mono12p")))
    with pytest.raises(profile.ProfileError, match="'packing' needs version 2"):
        profile.load(tmp_path / "mixed.json")
    (tmp_path / "bad.json").write_text(json.dumps(dict(doc, alignment=3)))
    with pytest.raises(profile.ProfileError, match="'alignment' must be a string"):
        profile.load(tmp_path / "bad.json")


def _push_frames(gst, prof_path, w, h, buffers):
    """appsrc (caps GRAY16_LE w x h, as aravissrc labels Mono12Packed) ! nrvalidity ! appsink: returns
    (list of (values, state), error text or None)."""
    from gst_plugins.elements._common import map_sample
    pipe = gst.parse_launch(f"appsrc name=src format=time caps=video/x-raw,format=GRAY16_LE,width={w},height={h},"
                            f"framerate=10/1 ! nrvalidity profile={prof_path} ! appsink name=sink sync=false")
    src, sink = pipe.get_by_name("src"), pipe.get_by_name("sink")
    pipe.set_state(gst.State.PLAYING)
    out, err = [], None
    try:
        for i, data in enumerate(buffers):
            buf = gst.Buffer.new_wrapped(bytes(data))
            buf.pts = i * gst.SECOND // 10
            src.emit("push-buffer", buf)
        src.emit("end-of-stream")
        while True:
            smp = sink.try_pull_sample(20 * gst.SECOND)
            if smp is None:
                break
            with map_sample(smp) as (v, s):
                out.append((v.copy(), s.copy()))
        msg = pipe.get_bus().pop_filtered(gst.MessageType.ERROR)
        if msg is not None:
            err = msg.parse_error()[0].message
    finally:
        pipe.set_state(gst.State.NULL)
    return out, err


@pytest.mark.gst
def test_nrvalidity_unpacks_packed_frames_labelled_gray16(gst, tmp_path):
    w, h = 16, 6
    base = profile.default(h, w, seed=8)
    codes = [np.random.default_rng(i).integers(0, 4096, (h, w)).astype(np.uint16) for i in range(3)]
    packed = profile.make(base.mask, bit_depth=12, packing="mono12packed")
    f = profile.save(packed, tmp_path / "packed.json")
    frames, err = _push_frames(gst, f, w, h, [pack_mono12packed(c) for c in codes])
    assert err is None and len(frames) == 3
    for (v, s), c in zip(frames, codes):
        v2, s2 = V.classify(c, base, dark_policy="weighted")      # nrvalidity's default dark policy
        assert np.array_equal(v, v2) and np.array_equal(s, s2)
    # the same packed bytes with a profile that says unpacked: an error naming the packing, not garbage
    plain = profile.save(base, tmp_path / "plain.json")
    frames, err = _push_frames(gst, plain, w, h, [pack_mono12packed(codes[0])])
    assert frames == [] and err is not None
    assert "144 bytes is a 12-bit packed 16x6 frame (mono12p or mono12packed) labelled GRAY16_LE" in err
    assert "plain.json" in err
    # unpacked frames with a profile that says packed
    frames, err = _push_frames(gst, f, w, h, [codes[0].astype("<u2").tobytes()])
    assert frames == [] and "packed.json says mono12packed" in err and "got 192 bytes" in err
