"""`nrhdr launch`, `nrhdr inspect`: gst-launch-1.0 / gst-inspect-1.0 with the nrhdr elements found; `nrhdr env`:
the environment plain gst-launch-1.0 / gst-inspect-1.0 need to find them, printed as shell exports for
`eval "$(nrhdr env)"` (gst_plugins.runtime.gst_env)."""
from __future__ import annotations

import argparse
import shlex

ENV_VARS = ("GST_PLUGIN_PATH", "PYTHONPATH", "GST_REGISTRY")


def exports(base: dict | None = None) -> str:
    """`export NAME='value'` lines (POSIX shell quoting) for GST_PLUGIN_PATH, PYTHONPATH (project root +
    this interpreter's site-packages + what was set) and a private GST_REGISTRY."""
    from .. import runtime
    env = runtime.gst_env(base)
    return "\n".join(f"export {k}={shlex.quote(env[k])}" for k in ENV_VARS) + "\n"


def python_note(base: dict | None = None) -> str | None:
    """What to do when a `python3` other than the one GStreamer's Python plugin loader embeds comes first on
    PATH (pyenv, conda): plain gst-launch-1.0 would then load no nrhdr element. None when there is no such
    conflict. (`nrhdr launch` and pipelines/*.sh set PYTHONHOME themselves.)"""
    from .. import runtime
    exe = runtime.path_python_conflict(base)
    if exe is None:
        return None
    ver, home = runtime.embedded_python(base)
    return (f"nrhdr env: warning: {exe} comes first on PATH, but GStreamer's Python plugin loader embeds Python "
            f"{ver} of {home}, which would then load that python3's library and fail (\"pygobject initialization "
            f"failed\", no nrhdr elements). Run plain gst-launch-1.0 as 'PYTHONHOME={home} gst-launch-1.0 ...' "
            f"(PYTHONHOME is not exported here: it would break that python3), or use 'nrhdr launch', which "
            f"sets it.")


def cmd_env(a) -> int:
    import sys
    print(exports(), end="")
    note = python_note()
    if note:
        print(note, file=sys.stderr)
    return 0


def cmd_launch(a) -> int:
    from .. import runtime
    return runtime.launch(a.args, until_exit=True)     # the process ends with the run


def cmd_inspect(a) -> int:
    from .. import runtime
    return runtime.inspect(a.args)


def add_launch(sub) -> None:
    p = sub.add_parser("launch", help="gst-launch-1.0 with the nrhdr elements found",
                       prefix_chars="\0")
    p.add_argument("args", nargs=argparse.REMAINDER)
    p.set_defaults(func=cmd_launch)


def add_inspect(sub) -> None:
    p = sub.add_parser("inspect", help="gst-inspect-1.0 with the nrhdr elements found", prefix_chars="\0")
    p.add_argument("args", nargs=argparse.REMAINDER)
    p.set_defaults(func=cmd_inspect)


def add_env(sub) -> None:
    p = sub.add_parser("env", help="print shell exports for plain gst-launch-1.0: eval \"$(nrhdr env)\"",
                       description="Print the exports (GST_PLUGIN_PATH, PYTHONPATH with the venv's "
                                   "site-packages, a private GST_REGISTRY) that let plain gst-launch-1.0 and "
                                   "gst-inspect-1.0 load the nrhdr elements. Use: eval \"$(nrhdr env)\"")
    p.set_defaults(func=cmd_env)
