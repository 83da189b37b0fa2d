"""Running nrhdr pipelines: environment for gst-launch-1.0 / gst-inspect-1.0 subprocesses (the Python
plugin loader embeds /usr/bin/python3 and must be told where the project and the venv's packages are) and an
in-process runner for apps.

- `plugin_dir()`: the folder holding `python/` (the loader shims) -> GST_PLUGIN_PATH.
- `gst_env(base=None)`: a copy of `base` (default os.environ) with GST_PLUGIN_PATH, PYTHONPATH and a
  private GST_REGISTRY set.
- `launch(args)` / `inspect(args)`: run gst-launch-1.0 -e / gst-inspect-1.0 with that environment and
  return the exit code.
- `run_pipeline(description, on_message=None)`: register the elements in this process, run the pipeline
  until EOS or error, return 0 / 1 (errors printed to stderr with the element's name).
"""
from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
import sysconfig
import tempfile
from pathlib import Path

_PKG_DIR = Path(__file__).resolve().parent          # <root>/gst_plugins
PROJECT_ROOT = _PKG_DIR.parent                      # holds nrhdr_core/ and gst_plugins/


def plugin_dir() -> Path:
    """The folder that holds `python/` with the loader shims (GST_PLUGIN_PATH entry)."""
    return _PKG_DIR


def _site_packages() -> list[str]:
    out = []
    for key in ("purelib", "platlib"):
        p = sysconfig.get_paths().get(key)
        if p and p not in out and os.path.isdir(p):
            out.append(p)
    return out


def _code_fingerprint(extra: str = "") -> str:
    """Hash of the element and loader sources (names, sizes, mtimes), the interpreter and `extra` (what the
    embedded Python depends on): a new registry file whenever they change, so a cached failed import never
    sticks (docs: gstreamer-python.md)."""
    h = hashlib.sha1()
    h.update(sys.executable.encode())
    h.update(extra.encode())
    h.update(str(PROJECT_ROOT).encode())
    for d in (_PKG_DIR / "python", _PKG_DIR / "elements"):  # core modules are imported lazily in do_start
        try:
            entries = sorted(d.glob("*.py"))
        except OSError:
            continue
        for f in entries:
            try:
                st = f.stat()
            except OSError:
                continue
            h.update(f"{f.name}:{st.st_size}:{st.st_mtime_ns};".encode())
    return h.hexdigest()[:16]


def _registry_file(extra: str = "") -> str:
    name = f"registry-{_code_fingerprint(extra)}.bin"
    for base in (Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "nrhdr",
                 Path(tempfile.gettempdir()) / f"nrhdr-{os.getuid() if hasattr(os, 'getuid') else 0}"):
        try:
            base.mkdir(parents=True, exist_ok=True)
            if os.access(base, os.W_OK):
                for old in base.glob("registry-*.bin"):  # keep the folder small
                    if old.name != name:
                        try:
                            old.unlink()
                        except OSError:
                            pass
                return str(base / name)
        except OSError:
            continue
    return str(Path(tempfile.mkdtemp(prefix="nrhdr-registry-")) / name)


def _prepend(value: str | None, entries: list[str]) -> str:
    parts = list(entries)
    for p in (value or "").split(os.pathsep):
        if p and p not in parts:
            parts.append(p)
    return os.pathsep.join(parts)


_PLUGIN_DIRS = ("/usr/lib/x86_64-linux-gnu/gstreamer-1.0", "/usr/lib/aarch64-linux-gnu/gstreamer-1.0",
                "/usr/lib64/gstreamer-1.0", "/usr/lib/gstreamer-1.0", "/usr/local/lib/gstreamer-1.0")


def embedded_python(env: dict | None = None) -> tuple[str, str] | None:
    """(version "3.11", home "/usr") of the Python that GStreamer's Python plugin loader (libgstpython.so,
    gst-python) embeds: the libpython it links, at the prefix of the matching system Python. None when the
    loader or that Python's standard library is not found."""
    import re
    env = os.environ if env is None else env
    dirs = [d for d in env.get("GST_PLUGIN_SYSTEM_PATH_1_0", env.get("GST_PLUGIN_SYSTEM_PATH", "")).split(
        os.pathsep) if d] + list(_PLUGIN_DIRS)
    for d in dirs:
        lib = Path(d) / "libgstpython.so"
        try:
            m = re.search(rb"libpython(3\.\d+)", lib.read_bytes())
        except OSError:
            continue
        if m is None:
            continue
        ver = m.group(1).decode()
        homes = ([sys.base_prefix] if f"{sys.version_info[0]}.{sys.version_info[1]}" == ver else []) + ["/usr"]
        for home in homes:
            if (Path(home) / "lib" / f"python{ver}" / "os.py").is_file():
                return ver, home
    return None


def path_python_conflict(env: dict | None = None) -> str | None:
    """The `python3` first on PATH when it is not the embedded Python (`embedded_python`): a pyenv or conda
    python3 there makes the embedded interpreter load that installation's library (CPython finds its home
    through `python3` on PATH), and the plugin loader then fails ("pygobject initialization failed", no
    nrhdr elements). None when there is no conflict (or nothing to compare)."""
    env = os.environ if env is None else env
    emb = embedded_python(env)
    exe = shutil.which("python3", path=env.get("PATH", ""))
    if emb is None or exe is None:
        return None
    ver, home = emb
    real = Path(os.path.realpath(exe))
    ok = {Path(os.path.realpath(Path(home) / "bin" / n)) for n in ("python3", f"python{ver}")}
    if real in ok:
        return None
    if not (real.parent.parent / "lib" / f"python{ver}" / "os.py").is_file() and not any(
            (d / "pyvenv.cfg").is_file() for d in (Path(exe).parent, Path(exe).parent.parent)):
        return None     # no library of that version there (e.g. a pyenv shim): CPython keeps its own home
    for cfg in (Path(exe).parent / "pyvenv.cfg", Path(exe).parent.parent / "pyvenv.cfg"):
        try:   # a venv made from the embedded Python is fine: CPython follows its `home`
            for line in cfg.read_text().splitlines():
                k, _, v = line.partition("=")
                if k.strip() == "home" and {Path(os.path.realpath(Path(v.strip()) / n))
                                            for n in ("python3", f"python{ver}")} & ok:
                    return None
        except OSError:
            continue
    return exe


def gst_env(base: dict | None = None) -> dict:
    """Environment for gst-launch-1.0 / gst-inspect-1.0 subprocesses that load the nrhdr elements.

    GST_PLUGIN_PATH gets plugin_dir(); PYTHONPATH gets the project root (nrhdr_core, gst_plugins) and this
    interpreter's site-packages (numpy, numba, OpenImageIO of the venv) before any existing entries;
    GST_REGISTRY is a private file (~/.cache/nrhdr/, else a temp dir) unless `base` already sets one.
    PYTHONHOME is set to the embedded Python's home when another `python3` comes first on PATH
    (`path_python_conflict`), unless `base` sets PYTHONHOME."""
    env = dict(os.environ if base is None else base)
    if not env.get("PYTHONHOME") and path_python_conflict(env) is not None:
        env["PYTHONHOME"] = embedded_python(env)[1]
    env["GST_PLUGIN_PATH"] = _prepend(env.get("GST_PLUGIN_PATH"), [str(plugin_dir())])
    env["PYTHONPATH"] = _prepend(env.get("PYTHONPATH"), [str(PROJECT_ROOT)] + _site_packages())
    if not env.get("GST_REGISTRY"):
        py = shutil.which("python3", path=env.get("PATH", "")) or ""
        env["GST_REGISTRY"] = _registry_file(f"{env.get('PYTHONHOME', '')}|{os.path.realpath(py) if py else ''}")
    # The scan may run in gst-plugin-scanner (fork) or in-process: both see the env above. Python
    # output should not be buffered so element tracebacks interleave with gst-launch output.
    env.setdefault("PYTHONUNBUFFERED", "1")
    return env


def _tool(name: str) -> str:
    exe = shutil.which(name)
    if exe is None:
        raise FileNotFoundError(f"{name} not found: install gstreamer1.0-tools (scripts/setup.sh does)")
    return exe




# Signals a wrapper turns into a clean stop of its gst-launch child (SIGINT = EOS with `gst-launch -e`).
STOP_SIGNALS = ("SIGINT", "SIGTERM", "SIGHUP")
STOP_TIMEOUT_S = 10.0   # after the EOS request: then SIGTERM, and SIGKILL KILL_TIMEOUT_S later
KILL_TIMEOUT_S = 5.0
DUPLICATE_S = 1.0       # a second signal within this time of the first is the same request, not an escalation
QUIET_S = 0.2          # after a stop, the handlers are restored only once no copy arrived for this long


def _stop_timeout() -> float:
    """Seconds a child gets to finish its files after SIGINT (env NRHDR_STOP_TIMEOUT, default 10); a value
    that is not a positive finite number is reported and the default used."""
    import math
    text = os.environ.get("NRHDR_STOP_TIMEOUT")
    if text is None:
        return STOP_TIMEOUT_S
    try:
        v = float(text)
    except ValueError:
        v = float("nan")
    if not (math.isfinite(v) and v > 0):
        print(f"nrhdr: NRHDR_STOP_TIMEOUT={text!r} is not a positive number of seconds; using "
              f"{STOP_TIMEOUT_S:g}", file=sys.stderr)
        return STOP_TIMEOUT_S
    return v


class StopSignals:
    """SIGINT, SIGTERM and SIGHUP as stop requests for a loop that polls `take()` (a context manager).

    The handler only records the signal: a second signal can run a Python handler nested between any two
    bytecodes of the first (a terminal's Ctrl-C to the process group and a script forwarding it arrive
    together), so all decisions are taken in the caller's loop, which never nests. A signal within
    DUPLICATE_S of the first is the same request and is dropped. Installs nothing outside the main
    thread. `restore=False` (a command whose process ends with the run) keeps the
    handler after the block: a late copy of the same stop must not raise KeyboardInterrupt in the exit.
    With `restore`, the old handlers come back only once the copies of a stop request have stopped arriving
    (QUIET_S without one, at most DUPLICATE_S after the first), so none reaches the caller as a
    KeyboardInterrupt."""

    def __init__(self, enabled: bool = True, restore: bool = True):
        self.enabled = enabled
        self.restore = restore
        self.got: list[int] = []        # distinct stop requests, in order
        self._first = 0.0
        self._arrived: list[tuple[int, float]] = []
        self._old: dict = {}
        self._last = 0.0                # when the last signal arrived (monotonic)

    def _on_signal(self, signum, frame):
        import time
        self._last = time.monotonic()
        self._arrived.append((signum, self._last))

    def __enter__(self):
        import signal
        import threading
        if self.enabled and threading.current_thread() is threading.main_thread():
            for name in STOP_SIGNALS:
                sig = getattr(signal, name, None)
                if sig is not None:
                    try:
                        self._old[sig] = signal.signal(sig, self._on_signal)
                    except (OSError, ValueError):
                        pass
        return self

    def __exit__(self, *exc):
        import signal
        if not self.restore:
            return False
        self._wait_quiet()
        for sig, h in self._old.items():
            try:
                signal.signal(sig, h)
            except (OSError, ValueError):
                pass
        self._old = {}
        return False

    def _wait_quiet(self) -> None:
        import time
        if not self._last:
            return
        first = self._first or self._last
        while True:
            now = time.monotonic()
            if now - self._last >= QUIET_S or now - first >= DUPLICATE_S:
                return
            time.sleep(0.01)

    def add(self, signum: int, at: float) -> bool:
        """Record one stop request; False when it duplicates the first (within DUPLICATE_S)."""
        if self.got and at - self._first < DUPLICATE_S:
            return False
        if not self.got:
            self._first = at
        self.got.append(signum)
        return True

    def take(self) -> list[tuple[int, float]]:
        """The new stop requests since the last call: (signal number, seconds after the first request)."""
        new = []
        while self._arrived:
            signum, at = self._arrived.pop(0)
            if self.add(signum, at):
                new.append((signum, at - self._first))
        return new


def _child_preexec_factory():
    """preexec_fn for a gst-launch child on Linux: its own process group (a terminal's Ctrl-C reaches only
    the wrapper, which forwards exactly one SIGINT: gst-launch dies on a second one) and
    PR_SET_PDEATHSIG=SIGINT (the child stops with EOS even when the wrapper is killed hard, e.g. SIGKILL).
    None where prctl is unavailable (then only the process group is set)."""
    parent = os.getpid()
    prctl = None
    if sys.platform.startswith("linux"):
        try:
            import ctypes
            libc = ctypes.CDLL(None, use_errno=True)
            prctl = libc.prctl
        except (OSError, AttributeError):
            prctl = None
    import signal as _signal
    sigint = int(_signal.SIGINT)

    sigpipe = getattr(_signal, "SIGPIPE", None)

    def preexec():  # runs in the forked child before exec
        os.setpgid(0, 0)
        if sigpipe is not None:   # if the wrapper dies, stderr writes must not kill a pipeline finishing
            _signal.signal(sigpipe, _signal.SIG_IGN)   # its files (SIG_IGN survives exec)
        if prctl is not None:
            prctl(1, sigint, 0, 0, 0)          # PR_SET_PDEATHSIG = 1
            if os.getppid() != parent:         # the wrapper died before prctl took effect
                os.kill(os.getpid(), sigint)
    return preexec


def _exit_status(rc: int) -> int:
    """Popen return code -> shell-style status (128 + signal for a child killed by a signal)."""
    return 128 - rc if rc < 0 else rc


class StderrFilter:
    """gst-launch's stderr as nrhdr passes it on (`feed(line)` -> the line to print, or None): drops an exact
    repeat of an `ERROR:` line already printed (gst-launch prints "ERROR: pipeline doesn't want to preroll."
    once per error message) and, after a first element error, the
    "Internal data stream error." block that upstream elements post as its consequence (a source or parser
    stopping because of that error: "streaming stopped, reason error / not-negotiated")."""

    def __init__(self):
        self.seen_error = False
        self.printed: set[str] = set()
        self.skipping = False

    def feed(self, line: str) -> str | None:
        s = line.rstrip("\r\n")
        if self.skipping:
            if s.startswith("streaming stopped, reason"):
                self.skipping = False
                return None
            if not (s.startswith(("ERROR:", "WARNING:", "INFO:", "nrhdr:")) or s == ""):
                return None
            self.skipping = False
        if s.startswith("ERROR: from element") and s.endswith("Internal data stream error.") and self.seen_error:
            self.skipping = True
            return None
        if s.startswith("ERROR:"):
            if s in self.printed:
                return None
            self.printed.add(s)
            self.seen_error = self.seen_error or s.startswith("ERROR: from element")
        return line


class QosTally:
    """QoS messages in gst-launch -m output ('Got message #N from element "E" (qos): ..., processed=(guint64)P,
    dropped=(guint64)D'): the last counts per element, and the report when a live pipeline dropped more
    frames than it showed."""
    import re as _re
    _RX = _re.compile(r'Got message #\d+ from element "([^"]+)" \(qos\):.*processed=\(guint64\)(\d+), '
                      r'dropped=\(guint64\)(\d+)')

    def __init__(self):
        self.counts: dict[str, tuple[int, int]] = {}

    def feed(self, line: str) -> None:
        m = self._RX.search(line)
        if m:
            self.counts[m.group(1)] = (int(m.group(2)), int(m.group(3)))

    def report(self) -> str | None:
        """Frames shown: the fewest any QoS element let through (the sink's rendered ones); dropped: the sum
        of all elements' drops. A report when more were dropped than shown."""
        if not self.counts:
            return None
        shown = min(done for done, _ in self.counts.values())
        dropped = sum(d for _, d in self.counts.values())
        if dropped <= shown:
            return None
        who = ", ".join(f"{name} {d}" for name, (_, d) in sorted(self.counts.items()) if d)
        return (f"nrhdr: the live display showed only {shown} of {shown + dropped} frames (dropped as late by "
                f"QoS: {who}): the chain is too slow for the frame rate; use cheaper settings (nrcrosstalk "
                f"mode=lut, nrreconstruct method=preview or auto, a lower FPS)")


def _call_filtered(cmd: list[str], env: dict, forward_signals: bool = False, until_exit: bool = False,
                   qos: QosTally | None = None, show_messages: bool = True) -> int:
    """Run `cmd`, passing its stderr through `StderrFilter`. With `qos`, stdout is read too: QoS messages
    are tallied and the report printed at the end; `show_messages=False` hides gst-launch's "Got message"
    lines (the -m that nrhdr added itself).

    With `forward_signals` (gst-launch children) SIGINT, SIGTERM and SIGHUP to this process become one
    SIGINT to the child (EOS: it finishes its files), escalated to SIGTERM after NRHDR_STOP_TIMEOUT s
    (default 10) and SIGKILL 5 s later; a second signal (more than 1 s after the first) escalates at once.
    The child runs in its own process group and gets SIGINT if this process dies (PR_SET_PDEATHSIG), so it
    is never left running alone. `until_exit`: see `launch`.
    Returns 128 + signal number when a signal stopped the run (130 SIGINT, 143 SIGTERM), else the child's
    status (128 + n when the child itself died of signal n)."""
    import signal
    import threading
    import time
    preexec = _child_preexec_factory() if forward_signals and os.name == "posix" else None
    proc = subprocess.Popen(cmd, env=env, stderr=subprocess.PIPE, bufsize=0, preexec_fn=preexec,
                            stdout=subprocess.PIPE if qos is not None else None)
    filt = StderrFilter()

    def pump_out():
        for raw in iter(proc.stdout.readline, b""):
            line = raw.decode(errors="replace")
            qos.feed(line)
            if show_messages or not line.startswith("Got message #"):
                sys.stdout.write(line)
                sys.stdout.flush()

    def pump():
        pending_blank = False
        for raw in iter(proc.stderr.readline, b""):
            line = filt.feed(raw.decode(errors="replace"))
            if line is None:
                pending_blank = False
                continue
            if line.strip() == "":
                if pending_blank:
                    sys.stderr.write("\n")
                pending_blank = True  # GLib puts a blank line before each critical: hold it back
                continue
            if pending_blank:
                sys.stderr.write("\n")
                pending_blank = False
            sys.stderr.write(line)
            sys.stderr.flush()

    t = threading.Thread(target=pump, daemon=True)
    t.start()
    t_out = None
    if qos is not None:
        t_out = threading.Thread(target=pump_out, daemon=True)
        t_out.start()
    # n: 0 running, 1 SIGINT sent, 2 SIGTERM sent, 3 SIGKILL sent; late: what passing the deadline means
    stage = {"n": 0, "deadline": None, "late": ""}

    def wait_for(seconds, what):
        stage["deadline"] = time.monotonic() + seconds
        stage["late"] = f"the pipeline did not stop within {seconds:g} s of {what}"

    def escalate(why):
        if proc.poll() is not None:
            return
        n = stage["n"]
        try:
            if n == 0:
                proc.send_signal(signal.SIGINT)
                wait_for(_stop_timeout(), "the EOS request")
            elif n == 1:
                print(f"nrhdr: {why}; terminating the pipeline", file=sys.stderr)
                proc.send_signal(signal.SIGTERM)
                wait_for(KILL_TIMEOUT_S, "SIGTERM")
            else:
                print(f"nrhdr: {why}; killing the pipeline", file=sys.stderr)
                proc.kill()
                stage["deadline"] = None
        except ProcessLookupError:
            return
        stage["n"] = min(n + 1, 3)

    def handle(stops):
        for signum, after in stops.take():
            name = signal.Signals(signum).name
            if len(stops.got) == 1:
                print(f"nrhdr: {name}: stopping the pipeline with EOS (files are finished; signal again "
                      f"to stop at once)", file=sys.stderr)
            escalate(f"{name} again {after:.1f} s after the first")

    with StopSignals(forward_signals, restore=not until_exit) as stops:
        try:
            while True:
                handle(stops)
                try:
                    rc = proc.wait(timeout=0.2)
                    break
                except subprocess.TimeoutExpired:
                    pass
                except KeyboardInterrupt:   # no handler installed (not the main thread): gst-launch -e
                    stops.add(int(signal.SIGINT), time.monotonic())  # got the same SIGINT from the terminal
                    continue
                if stage["deadline"] is not None and time.monotonic() > stage["deadline"]:
                    escalate(stage["late"])
            handle(stops)           # a signal in the child's last moments still sets the exit status
        except BaseException:
            if proc.poll() is None:     # never leave the child alone
                proc.kill()
                proc.wait()
            raise
        finally:
            t.join(timeout=5)
            if t_out is not None:
                t_out.join(timeout=5)
    if qos is not None and qos.report():
        print(qos.report(), file=sys.stderr)
    if stops.got:
        return 128 + stops.got[0]
    return _exit_status(rc)


def launch(args: list[str], until_exit: bool = False) -> int:
    """Run `gst-launch-1.0 -e <args>` with gst_env(); returns its exit status (non-zero on error).

    SIGINT/SIGTERM/SIGHUP stop the pipeline with EOS (see `_call_filtered`): the exit status is then 130 /
    143 / 129; the child never outlives this process. `until_exit` (`nrhdr launch`, whose process ends with
    the run): the stop-signal handler stays installed after the run (`StopSignals(restore=False)`).
    With NRHDR_REPORT_DROPS=1 in the environment (the live pipelines set it) gst-launch runs with -m and a
    pipeline that dropped more frames than it showed says so at the end (`QosTally`)."""
    try:
        exe = _tool("gst-launch-1.0")
    except FileNotFoundError as e:
        print(f"nrhdr: {e}", file=sys.stderr)
        return 127
    args = list(args)
    if "-e" not in args and "--eos-on-shutdown" not in args:
        args = ["-e"] + args
    qos, shown = None, True
    if os.environ.get("NRHDR_REPORT_DROPS") == "1":
        qos = QosTally()
        shown = "-m" in args or "--messages" in args
        if not shown:
            args = ["-m"] + args
    return _call_filtered([exe] + args, gst_env(), forward_signals=True, until_exit=until_exit, qos=qos,
                          show_messages=shown)


def inspect(args: list[str]) -> int:
    """Run `gst-inspect-1.0 <args>` with gst_env(); returns its exit code."""
    try:
        exe = _tool("gst-inspect-1.0")
    except FileNotFoundError as e:
        print(f"nrhdr: {e}", file=sys.stderr)
        return 127
    return _call_filtered([exe] + list(args), gst_env())


def run_pipeline(description: str, on_message=None) -> int:
    """Run a gst-launch style pipeline in this process with the nrhdr elements registered in-process.

    Blocks until EOS (returns 0) or the first error (prints `ERROR from <element>: <text>` and the debug
    text to stderr, returns 1). `on_message(msg)` is called for every bus message (e.g. the element messages
    "nrhdr-frame-stats" of nrreconstruct). In the main thread, SIGINT (Ctrl-C), SIGTERM or SIGHUP sends EOS so
    files are finished and the run then returns 128 + that signal (130 for Ctrl-C); a second one (more than
    1 s after the first) stops at once (`StopSignals`)."""
    import gst_plugins
    gst_plugins.register_all()
    from gi.repository import GLib, Gst

    try:
        pipeline = Gst.parse_launch(description)
    except GLib.Error as e:
        print(f"ERROR: invalid pipeline: {e.message}", file=sys.stderr)
        return 1
    if isinstance(pipeline, Gst.Element) and not isinstance(pipeline, Gst.Pipeline):
        p = Gst.Pipeline.new(None)
        p.add(pipeline)
        pipeline = p
    bus = pipeline.get_bus()
    result = {"rc": 1, "playing": False}

    def handle(msg) -> bool:
        """Return True when the run is over."""
        if on_message is not None:
            try:
                on_message(msg)
            except Exception as e:  # noqa: BLE001 - an app callback must not kill the run silently
                print(f"nrhdr: on_message callback failed: {type(e).__name__}: {e}", file=sys.stderr)
        t = msg.type
        if t == Gst.MessageType.EOS:
            result["rc"] = 0
            return True
        if t == Gst.MessageType.ERROR:
            err, dbg = msg.parse_error()
            src = msg.src.get_path_string() if msg.src is not None else "?"
            name = msg.src.get_name() if msg.src is not None else "?"
            print(f"ERROR from {name} ({src}): {err.message}", file=sys.stderr)
            if dbg:
                print(f"debug: {dbg}", file=sys.stderr)
            result["rc"] = 1
            return True
        if t == Gst.MessageType.WARNING:
            w, dbg = msg.parse_warning()
            name = msg.src.get_name() if msg.src is not None else "?"
            print(f"WARNING from {name}: {w.message}", file=sys.stderr)
        if t == Gst.MessageType.STATE_CHANGED and msg.src == pipeline:
            result["playing"] = msg.parse_state_changed()[1] == Gst.State.PLAYING
        if t == Gst.MessageType.LATENCY:  # an element's processing time grew: as gst-launch does
            pipeline.recalculate_latency()
        if t == Gst.MessageType.INFO:  # e.g. numba compiling inside the pipeline: never silent
            i, _dbg = msg.parse_info()
            print(f"INFO from {msg.src.get_name() if msg.src is not None else '?'}: {i.message}",
                  file=sys.stderr)
        return False

    import signal
    import threading
    stop_wait = None        # seconds the shutdown may take after a second stop request (None: no limit)
    eos_due = False         # a stop request waits for PLAYING: EOS into a live source that is still
                            # prerolling deadlocks GStreamer (gst-launch too sends it only when PLAYING)
    with StopSignals() as stops:
        ret = pipeline.set_state(Gst.State.PLAYING)
        try:
            if ret == Gst.StateChangeReturn.FAILURE:
                # the element that failed has usually posted an error: report it
                msg = bus.pop_filtered(Gst.MessageType.ERROR)
                if msg is not None:
                    handle(msg)
                else:
                    print("ERROR: the pipeline could not start (state change failed)", file=sys.stderr)
                return 1
            while True:
                for signum, after in stops.take():
                    if len(stops.got) > 1:
                        print(f"nrhdr: {signal.Signals(signum).name} again {after:.1f} s after the first; "
                              f"stopping now", file=sys.stderr)
                        stop_wait = KILL_TIMEOUT_S
                        return 128 + stops.got[0]
                    print(f"nrhdr: {signal.Signals(signum).name}: sending EOS so files are finished (signal "
                          f"again to stop now)", file=sys.stderr)
                    eos_due = True
                if eos_due and result["playing"]:
                    # from another thread: a live source takes the EOS only between two buffers, and a
                    # blocked main thread could not take the second signal
                    threading.Thread(target=pipeline.send_event, args=(Gst.Event.new_eos(),), daemon=True,
                                     name="nrhdr-eos").start()
                    eos_due = False
                msg = bus.timed_pop_filtered(100 * Gst.MSECOND, Gst.MessageType.ANY)
                if msg is not None and handle(msg):
                    # a stopped run is not a finished one: EOS after a stop request returns 128 + signal
                    return 128 + stops.got[0] if stops.got and result["rc"] == 0 else result["rc"]
        finally:
            if stop_wait is None:
                pipeline.set_state(Gst.State.NULL)
            else:   # asked twice: an element blocked in its streaming thread must not hold the stop
                t = threading.Thread(target=pipeline.set_state, args=(Gst.State.NULL,), daemon=True)
                t.start()
                t.join(stop_wait)
                if t.is_alive():
                    print(f"nrhdr: the pipeline did not shut down within {stop_wait:g} s (an element is "
                          f"blocked); leaving it", file=sys.stderr)
