"""Camera profiles for the elements: `nrhdr_core.profile.load` behind a small cache keyed on every file
the profile is made of (the JSON, the mask PNG and the crosstalk calibration it names, each with its
mtime and size), so a replaced mask or calibration is read again. The files a profile names must lie in
its folder (docs/RELIABILITY.md) unless the element's `allow-outside-paths` is set; a profile path that
arrives in the caps was accepted by the element upstream, and is read with that element's decision."""
from __future__ import annotations

import os
import threading

from ._props import Prop

ALLOW_OUTSIDE_PROP = Prop(
    "allow-outside-paths", bool, False, "Allow paths outside",
    "Read a profile (or clip folder) whose mask, calibration or frames file lies outside its folder (absolute, "
    "'..' or a symlink leaving it); refused by default, since these files may come from others "
    "(docs/RELIABILITY.md)")

_cache: dict = {}
_outside_allowed: set[str] = set()    # profiles read with allow_outside=True in this process
_lock = threading.Lock()
_MAX = 8


def _stat(path: str):
    try:
        st = os.stat(path)
        return (path, st.st_mtime_ns, st.st_size)
    except OSError:
        return (path, None, None)


def profile_files(path: str) -> list[str]:
    """The files the profile JSON at `path` reads: itself, its mask and its crosstalk calibration file
    (names relative to its folder, docs/PROFILE.md); only the JSON when it cannot be parsed."""
    from nrhdr_core import io
    out = [path]
    try:
        doc = io.read_json(path, "camera profile")
    except io.FileContentError:
        return out
    folder = os.path.dirname(path)
    names = [doc.get("mask")]
    xt = doc.get("crosstalk")
    if isinstance(xt, dict):
        names.append(xt.get("file"))
    out += [os.path.join(folder, n) for n in names if isinstance(n, str) and n]
    return out


def cache_key(path: str) -> tuple:
    return tuple(_stat(f) for f in profile_files(path))


def load_profile(path: str, allow_outside: bool = False, from_caps: bool = False):
    """nrhdr_core.profile.load through the cache; ProfileError (a ValueError) propagates with its message
    naming the file and the field. `from_caps`: the path came from upstream caps, so it is read as the
    upstream element read it (with or without `allow_outside`)."""
    from nrhdr_core import profile as profile_mod
    if not path:
        raise profile_mod.ProfileError("no camera profile set (property 'profile' is empty)")
    ap = os.path.abspath(os.path.expanduser(path))
    with _lock:
        allow_outside = bool(allow_outside) or (from_caps and ap in _outside_allowed)
    key = (allow_outside,) + cache_key(ap)
    with _lock:
        p = _cache.get(key)
    if p is not None:
        return p
    p = profile_mod.load(ap, allow_outside=allow_outside)
    if allow_outside:
        with _lock:
            _outside_allowed.add(ap)
    if key[1:] == cache_key(ap):          # unchanged while it was read: cache it
        with _lock:
            if len(_cache) >= _MAX:
                _cache.clear()
            _cache[key] = p
    return p
