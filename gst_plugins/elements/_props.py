"""The elements' property tables: each property declared once (type, real range or choices, default, nick,
blurb, whether it may change while PLAYING, controllable), from which the GObject properties, the enum
GTypes, the immutable settings snapshot and docs/ELEMENTS.md's tables are made.

- Choices are real GEnum types (registered with `g_enum_register_static` through ctypes: PyGObject 3.42
  cannot register a GEnum subclass from Python), so gst-launch refuses an unknown word ("could not set
  property") and gst-inspect lists the values.
- Numbers carry their real minimum and maximum. GObject refuses an out-of-range value before the element
  sees it (a GLib-GObject warning, the old value stays); a GLib log handler attributes that refusal to the
  element (the most recently made nrhdr element of this thread with that property: gst-launch sets the
  properties of each element right after making it), so the element fails to start with an error naming
  the property, the value and the range instead of running with its default. NaN is refused the same way.
- A property that cannot change while PAUSED/PLAYING (GST_PARAM_MUTABLE_READY) keeps its value and posts a
  WARNING naming it; the others (GST_PARAM_MUTABLE_PLAYING) swap the settings snapshot, which the
  streaming thread reads once per frame.
"""
from __future__ import annotations

import collections
import ctypes
import dataclasses
import math
import re
import threading
import weakref

from ._gst import GLib, GObject, Gst

MUTABLE_PLAYING = int(Gst.PARAM_MUTABLE_PLAYING)
MUTABLE_READY = int(Gst.PARAM_MUTABLE_READY)
CONTROLLABLE = int(Gst.PARAM_CONTROLLABLE)  # GstController curves (BaseTransform syncs them per frame)

INT_MAX = 2147483647
UINT64 = "uint64"


@dataclasses.dataclass(frozen=True)
class Prop:
    """One element property. `kind`: bool, int, float, str, UINT64, or a tuple of choice words (an enum).
    `playing`: may change while PAUSED/PLAYING. `readonly`: the value comes from the element's
    `nr_read(name)`."""
    name: str
    kind: object
    default: object
    nick: str
    blurb: str
    minimum: float | None = None
    maximum: float | None = None
    playing: bool = False
    controllable: bool = False
    readonly: bool = False

    @property
    def attr(self) -> str:
        return self.name.replace("-", "_")

    @property
    def choices(self) -> tuple[str, ...] | None:
        return self.kind if isinstance(self.kind, tuple) else None

    def range_text(self) -> str:
        if self.choices:
            return "one of " + ", ".join(self.choices)
        if self.minimum is not None:
            return f"{_num(self.minimum)} .. {_num(self.maximum)}"
        return ""


def _num(x) -> str:
    return f"{x:g}" if isinstance(x, float) else str(x)


# ---- enum GTypes --------------------------------------------------------------------------------------

class _EnumValue(ctypes.Structure):
    _fields_ = [("value", ctypes.c_int), ("value_name", ctypes.c_char_p), ("value_nick", ctypes.c_char_p)]


_keep = []                    # the GEnumValue arrays and strings GLib points at, alive for the process
_enums: dict = {}
_enum_lock = threading.Lock()


def enum_class(type_name: str, choices: tuple[str, ...], descriptions: dict | None = None):
    """The Python class of the GEnum `type_name` whose values 0..n-1 have the nicks `choices` (registered
    once per process)."""
    from gi import _gi
    with _enum_lock:
        cls = _enums.get(type_name)
        if cls is not None:
            return cls
        try:
            gtype = GObject.type_from_name(type_name)
        except RuntimeError:
            gtype = None
        if gtype is None or not gtype.is_a(GObject.TYPE_ENUM):
            lib = ctypes.CDLL("libgobject-2.0.so.0")
            lib.g_enum_register_static.restype = ctypes.c_size_t
            lib.g_enum_register_static.argtypes = [ctypes.c_char_p, ctypes.c_void_p]
            arr = (_EnumValue * (len(choices) + 1))()
            strings = []
            for i, word in enumerate(choices):
                name = ctypes.create_string_buffer(((descriptions or {}).get(word) or word).encode())
                nick = ctypes.create_string_buffer(word.encode())
                strings += [name, nick]
                arr[i].value = i
                arr[i].value_name = ctypes.cast(name, ctypes.c_char_p)
                arr[i].value_nick = ctypes.cast(nick, ctypes.c_char_p)
            tname = ctypes.create_string_buffer(type_name.encode())
            _keep.append((arr, strings, tname))
            if not lib.g_enum_register_static(ctypes.cast(tname, ctypes.c_char_p), ctypes.addressof(arr)):
                raise RuntimeError(f"cannot register the enum type {type_name}")
            gtype = GObject.type_from_name(type_name)
        cls = _gi.enum_add(gtype)
        _enums[type_name] = cls
        return cls


class PropertyTable:
    """The properties of one element class (`Prop`s); `gtype_name` prefixes its enum type names."""

    def __init__(self, gtype_name: str, props, descriptions: dict | None = None):
        self.gtype_name = gtype_name
        self.props = {p.name: p for p in props}
        self.enums = {}
        for p in self.props.values():
            if p.choices:
                camel = "".join(w.capitalize() for w in p.name.split("-"))
                self.enums[p.name] = enum_class(f"{gtype_name}{camel}", p.choices, (descriptions or {}).get(p.name))
                if p.default not in p.choices:
                    raise ValueError(f"{gtype_name}.{p.name}: default {p.default!r} not in {p.choices}")
        fields = [p.attr for p in self.props.values() if not p.readonly]
        self.Settings = collections.namedtuple(f"{gtype_name}Settings", fields)

    def __iter__(self):
        return iter(self.props.values())

    def __getitem__(self, name: str) -> Prop:
        return self.props[name]

    def defaults(self):
        return self.Settings(**{p.attr: p.default for p in self.props.values() if not p.readonly})

    def gproperties(self) -> dict:
        """The `__gproperties__` of the element class."""
        out = {}
        for p in self.props.values():
            flags = GObject.ParamFlags.READABLE if p.readonly else GObject.ParamFlags.READWRITE
            if not p.readonly:
                flags |= MUTABLE_PLAYING if p.playing else MUTABLE_READY
            if p.controllable:
                flags |= CONTROLLABLE
            if p.choices:
                cls = self.enums[p.name]
                out[p.name] = (cls, p.nick, p.blurb, cls(p.choices.index(p.default)), flags)
            elif p.kind is bool or p.kind is str:
                out[p.name] = (p.kind, p.nick, p.blurb, p.default, flags)
            else:
                t = {int: GObject.TYPE_INT, float: GObject.TYPE_DOUBLE, UINT64: GObject.TYPE_UINT64}[p.kind]
                lo = p.minimum if p.minimum is not None else (0 if p.kind is UINT64 else -INT_MAX - 1)
                hi = p.maximum if p.maximum is not None else (2 ** 64 - 1 if p.kind is UINT64 else INT_MAX)
                out[p.name] = (t, p.nick, p.blurb, lo, hi, p.default, flags)
        return out

    def check(self, name: str, value) -> tuple[object, str | None]:
        """(converted value, None) or (None, why it is refused)."""
        p = self.props[name]
        if p.choices:
            if isinstance(value, str):
                v = value.strip().lower()
            else:
                i = int(value)
                v = p.choices[i] if 0 <= i < len(p.choices) else None
            if v not in p.choices:
                return None, f"invalid value {value!r} for property '{name}' ({p.range_text()})"
            return v, None
        if p.kind is bool:
            return bool(value), None
        if p.kind is str:
            return ("" if value is None else str(value)), None
        v = float(value) if p.kind is float else int(value)
        if p.kind is float and not math.isfinite(v):
            return None, f"invalid value {value!r} for property '{name}' (a finite number, {p.range_text()})"
        if (p.minimum is not None and v < p.minimum) or (p.maximum is not None and v > p.maximum):
            return None, f"value {_num(v)} for property '{name}' is out of range ({p.range_text()})"
        return v, None

    def markdown(self) -> str:
        """The property table of docs/ELEMENTS.md."""
        rows = ["| Property | Type | Range / values | Default | While playing | Description |",
                "|---|---|---|---|---|---|"]
        for p in self.props.values():
            kind = ("enum" if p.choices else {bool: "bool", int: "int", float: "double", str: "string",
                                               UINT64: "uint64"}[p.kind])
            default = ("" if p.readonly else f"`{str(p.default).lower()}`" if p.kind is bool else
                       f"`{p.default}`" if p.default != "" else '`""`')
            mut = "read-only" if p.readonly else ("yes" if p.playing else "no")
            if p.controllable:
                mut += ", controllable"
            blurb = p.blurb.replace("|", "\\|")
            rows.append(f"| `{p.name}` | {kind} | {p.range_text()} | {default} | {mut} | {blurb} |")
        return "\n".join(rows)


# ---- refusals GObject makes before the element sees a value ---------------------------------------------

_recent = threading.local()
_REFUSED = re.compile(r"value \"(?P<value>.*)\" of type '[^']*' is invalid or out of range for property "
                      r"'(?P<prop>[^']+)'")
_handler_lock = threading.Lock()
_handler_installed = False


def remember_element(element) -> None:
    """Called by each new element: the candidates a GObject range refusal in this thread is attributed to."""
    lst = getattr(_recent, "elements", None)
    if lst is None:
        lst = _recent.elements = collections.deque(maxlen=32)
    lst.append(weakref.ref(element))


def _attribute(prop: str, value: str) -> bool:
    for ref in reversed(getattr(_recent, "elements", ()) or ()):
        el = ref()
        if el is not None and prop in type(el).PROPERTIES.props:
            el.nr_refused(prop, value)
            return True
    return False


def install_refusal_handler() -> None:
    """A GLib-GObject log handler (chained to GLib's default handler, so the warning is still printed)
    that turns a range refusal of an nrhdr element's property into a settings error of that element."""
    global _handler_installed
    with _handler_lock:
        if _handler_installed:
            return
        _handler_installed = True

    def handler(domain, level, message, *user):
        try:
            m = _REFUSED.search(message or "")
            if m is not None:
                _attribute(m.group("prop"), m.group("value"))
        except Exception:  # noqa: BLE001 - a log handler never raises
            pass
        GLib.log_default_handler(domain, level, message, None)

    GLib.log_set_handler("GLib-GObject", GLib.LogLevelFlags.LEVEL_WARNING | GLib.LogLevelFlags.LEVEL_CRITICAL,
                         handler, None)


class Properties:
    """Mixin: GObject property access through the class's `PROPERTIES` table. `self.settings` is an
    immutable snapshot swapped whole on each change (read it once per frame). Hooks: `nr_read(name)` for
    read-only properties, `nr_property_changed(name, value)` after a change."""

    PROPERTIES: PropertyTable = None

    def __init_subclass__(cls, **kw):
        super().__init_subclass__(**kw)
        table = cls.__dict__.get("PROPERTIES")
        if table is not None and "__gproperties__" not in cls.__dict__:
            cls.__gproperties__ = table.gproperties()

    def nr_props_init(self) -> None:
        self.settings = type(self).PROPERTIES.defaults()
        self._nr_invalid = {}
        install_refusal_handler()
        remember_element(self)

    def set_property(self, name, value):
        """Python's `set_property`: a number out of range or NaN raises ValueError naming the property,
        the value and the range (GObject would only print a warning and keep the old value)."""
        table = type(self).PROPERTIES
        p = table.props.get(name) or table.props.get(str(name).replace("_", "-"))
        if p is not None and p.kind in (int, float) and not isinstance(value, bool):
            try:
                _v, err = table.check(p.name, value)
            except (TypeError, ValueError, OverflowError):
                err = None                   # not a number: PyGObject's own TypeError follows
            if err is not None:
                raise ValueError(f"{self.get_name()}: {err}")
        return super().set_property(name, value)

    def do_get_property(self, pspec):
        p = type(self).PROPERTIES[pspec.name]
        if p.readonly:
            return self.nr_read(p.name)
        v = getattr(self.settings, p.attr)
        return type(self).PROPERTIES.enums[p.name](p.choices.index(v)) if p.choices else v

    def do_set_property(self, pspec, value):
        table = type(self).PROPERTIES
        p = table[pspec.name]
        v, err = table.check(p.name, value)
        if err is not None:
            self.nr_refuse_text(p.name, err)
            return
        old = getattr(self.settings, p.attr)
        if not p.playing and v != old and self._nr_running():
            self.nr_warning(f"property '{p.name}' cannot change while PAUSED or PLAYING (set it in NULL or "
                            f"READY); keeping {old!r}")
            return
        self._nr_invalid.pop(p.name, None)
        self.settings = self.settings._replace(**{p.attr: v})
        self.nr_property_changed(p.name, v)

    def nr_property_changed(self, name: str, value) -> None:
        """Hook: a property changed (default: nothing)."""

    def nr_read(self, name: str):
        raise NotImplementedError(name)

    def _nr_running(self) -> str:
        try:
            st = self.get_state(0)[1]
        except Exception:  # noqa: BLE001
            return ""
        return st.value_nick.upper() if st in (Gst.State.PAUSED, Gst.State.PLAYING) else ""

    def nr_refused(self, name: str, value: str) -> None:
        """GObject refused `value` for `name` (out of range): remember it with the range."""
        p = type(self).PROPERTIES[name]
        self.nr_refuse_text(name, f"value {value} for property '{name}' is out of range ({p.range_text()})")

    def nr_refuse_text(self, name: str, text: str) -> None:
        """A refused value: while PAUSED/PLAYING a WARNING (the old value stays); before start it is kept so
        that the start fails with an element error (`settings_errors`)."""
        if self._nr_running():
            p = type(self).PROPERTIES[name]
            self.nr_warning(f"{text}; keeping {getattr(self.settings, p.attr)!r}")
        else:
            self._nr_invalid[name] = text

    def settings_errors(self) -> list[str]:
        """Values refused since the last start, one text per property (property name, value, range)."""
        return list(self._nr_invalid.values())

    def nr_warning(self, text: str) -> None:
        self.message_full(Gst.MessageType.WARNING, Gst.core_error_quark(), int(Gst.CoreError.FAILED), text,
                          None, __file__, "set_property", 0)
