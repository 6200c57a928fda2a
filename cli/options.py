"""Command-line options that every covey CLI shares.

- joining the mesh (`--fleet --connect --listen --mesh-mode --zenoh-config`) and the member key
  file (`--key-file`, or $COVEY_FLEET_KEY_FILE);
- value types that refuse a bad value with a message naming its unit;
- flags built from a config dataclass: one per field, help from the docstring under the field;
- flags that are renamed or refused: accepted by the parser only to say why not, in one line;
- `die`: a set-up error as one line on stderr and exit status 2; `nobody_answered`: no
  router or peer at the endpoints, one line and exit status 1;
- `stop_on_signals`: SIGINT and SIGTERM set a threading.Event instead of raising.

It lives in cli/, on the floor above comms/ and trust/ (it builds mesh configs and names the key
file) and below policy/ (tests/test_import_layers.py): every command line can use it.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import logging
import math
import os
import signal
import sys
import threading
import typing
from collections.abc import Callable, Iterable, Iterator, Mapping
from typing import Any, NoReturn

from comms.geo import GeoOrigin
from comms.session import DEFAULT_PORT, MeshConfig, MeshConfigError
from trust.auth import ENV_KEY_FILE

UNIT_SUFFIXES: dict[str, str] = {
    "_m_s2": "m/s^2",
    "_m_s": "m/s",
    "_rad_s": "rad/s",
    "_1_s": "1/s",
    "_pct_s": "%/s",
    "_ms": "milliseconds",
    "_ns": "nanoseconds",
    "_s": "seconds",
    "_minutes": "minutes",
    "_m": "metres",
    "_hz": "Hz",
    "_pct": "%",
    "_rad": "radians",
    "_deg": "degrees",
}
"""Name endings that carry a unit (longest first), and the unit's name in messages."""


def setup_logging(
    verbose: bool, *, quiet_level: int = logging.WARNING, name: str = "%(name)s"
) -> None:
    """One log format for every covey process: INFO with -v (DEBUG where the quiet level is
    already INFO), else `quiet_level`."""
    loud = logging.DEBUG if quiet_level <= logging.INFO else logging.INFO
    logging.basicConfig(
        level=loud if verbose else quiet_level,
        format=f"%(asctime)s {name} %(levelname)s %(message)s",
    )


def unit_of(name: str) -> str | None:
    """The unit a field or flag name ends in ("cruise_speed_m_s" -> "m/s"), or None."""
    key = name.lstrip("-").replace("-", "_")
    return next((unit for end, unit in UNIT_SUFFIXES.items() if key.endswith(end)), None)


# -- set-up errors -------------------------------------------------------------------------------
def die(parser: argparse.ArgumentParser, message: str) -> NoReturn:
    """A set-up error (key file, roster, Zenoh config, endpoint): one line, exit status 2."""
    print(f"{parser.prog}: error: {' '.join(str(message).split())}", file=sys.stderr)
    raise SystemExit(2)


def nobody_answered(parser: argparse.ArgumentParser, exc: BaseException) -> int:
    """A tool found nobody at its endpoints (comms.session.MeshUnreachable): one line on
    stderr naming them, and exit status 1 (it ran; there was nothing to talk to)."""
    print(f"{parser.prog}: {' '.join(str(exc).split())}", file=sys.stderr)
    return 1


# -- value types ---------------------------------------------------------------------------------
def port(text: str) -> int:
    """A TCP port, 0..65535 (0 = any free port)."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a port number") from None
    if not 0 <= v <= 65535:
        raise argparse.ArgumentTypeError(f"{v} is outside 0..65535")
    return v


def finite(
    unit: str,
    *,
    minimum: float | None = 0.0,
    inclusive: bool = False,
    allow_inf: bool = False,
    maximum: float | None = None,
) -> Callable[[str], float]:
    """A finite number of `unit` above `minimum` (or at least it, with `inclusive`; any finite
    number with minimum=None) and at most `maximum` (when given); with `allow_inf`, also "inf"
    (for "as fast as possible")."""
    if minimum is None:
        bound = ""
    else:
        bound = f" {'>=' if inclusive else '>'} {minimum:g}"
    if maximum is not None:
        bound += f"{' and' if bound else ''} <= {maximum:g}"

    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number of {unit}") from None
        ok = math.isfinite(v) or (allow_inf and v == math.inf)
        if ok and minimum is not None:
            ok = v >= minimum if inclusive else v > minimum
        if ok and maximum is not None:
            ok = v <= maximum
        if not ok:
            raise argparse.ArgumentTypeError(f"{text!r} must be a finite number of {unit}{bound}")
        return v

    parse.__name__ = f"number of {unit}"  # argparse names the type in some of its messages
    return parse


def floats(text: str, n: int, what: str) -> tuple[float, ...]:
    """`n` finite comma-separated numbers ("3,4"); `what` names the flag in the message."""
    try:
        values = tuple(float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{what} must be {n} comma-separated numbers, got {text!r}"
        ) from None
    if len(values) != n or not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(
            f"{what} must be {n} finite comma-separated numbers, got {text!r}"
        )
    return values


def geo_origin(text: str) -> GeoOrigin:
    """'LAT,LON,ALT' in degrees, degrees, metres -> GeoOrigin."""
    lat, lon, alt = floats(text, 3, "LAT,LON,ALT (degrees, degrees, metres)")
    try:
        return GeoOrigin(lat, lon, alt)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"{text!r}: {exc}") from None


MAX_HOSTED_VEHICLES = 10_000
"""The most vehicles one `covey agent --ids` process may host."""


def vehicle_ids(text: str) -> tuple[int, ...]:
    """Vehicle ids as ranges and single ids, comma-separated: "1-100", "1-50,60,70-79". Each id
    within the schema's range, ranges ascending, no id twice, at most MAX_HOSTED_VEHICLES."""
    from comms.schema import MAX_VEHICLE_ID

    def one(part: str) -> int:
        try:
            v = int(part)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"{text!r}: {part!r} is not a vehicle id (ids and ranges: 1-50,60,70-79)"
            ) from None
        if not 1 <= v <= MAX_VEHICLE_ID:
            raise argparse.ArgumentTypeError(
                f"{text!r}: vehicle id {v} is outside 1..{MAX_VEHICLE_ID}"
            )
        return v

    ids: list[int] = []
    for part in (p.strip() for p in text.split(",")):
        if not part:
            raise argparse.ArgumentTypeError(f"{text!r}: an empty item (ids and ranges: 1-50,60)")
        lo, dash, hi = part.partition("-")
        if dash:
            a, b = one(lo.strip()), one(hi.strip())
            if a > b:
                raise argparse.ArgumentTypeError(f"{text!r}: range {part} runs backwards")
        else:
            a = b = one(part)
        if len(ids) + b - a + 1 > MAX_HOSTED_VEHICLES:  # said before building a huge list
            raise argparse.ArgumentTypeError(
                f"{text!r}: more than {MAX_HOSTED_VEHICLES} vehicles in one process"
            )
        ids.extend(range(a, b + 1))
    seen: set[int] = set()
    again: set[int] = set()
    for v in ids:
        (again if v in seen else seen).add(v)
    twice = sorted(again)
    if twice:
        more = ", ..." if len(twice) > 5 else ""
        raise argparse.ArgumentTypeError(
            f"{text!r}: vehicle id {', '.join(map(str, twice[:5]))}{more} given twice"
        )
    return tuple(ids)


def id_ranges(ids: Iterable[int]) -> str:
    """The shortest `vehicle_ids` text for `ids` (sorted): (1, 2, 3, 7) -> "1-3,7"."""
    out: list[str] = []
    run: list[int] = []
    for v in sorted(ids):
        if run and v == run[-1] + 1:
            run.append(v)
            continue
        if run:
            out.append(f"{run[0]}-{run[-1]}" if len(run) > 1 else str(run[0]))
        run = [v]
    if run:
        out.append(f"{run[0]}-{run[-1]}" if len(run) > 1 else str(run[0]))
    return ",".join(out)


def comma_list(text: str) -> tuple[str, ...]:
    """'a,b,,c' -> ('a', 'b', 'c')."""
    return tuple(s for s in text.split(",") if s)


# -- renamed and refused flags --------------------------------------------------------------------
class Refused(argparse.Action):
    """A flag the parser knows only to refuse, with the reason, in one line (exit status 2)."""

    def __init__(self, option_strings, dest, message: str = "", **kw) -> None:
        kw.update(nargs="?", default=argparse.SUPPRESS, help=kw.get("help", argparse.SUPPRESS))
        super().__init__(option_strings, dest, **kw)
        self.message = message

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        parser.error(self.message)


def refuse(
    parser: argparse.ArgumentParser | argparse._ArgumentGroup,
    flag: str,
    reason: str,
    show: bool = False,
) -> None:
    """`flag` is refused with `reason` (and listed in --help with it when `show`)."""
    parser.add_argument(
        flag,
        action=Refused,
        message=f"{flag} is refused: {reason}",
        dest=f"_refused_{flag.lstrip('-').replace('-', '_')}",
        metavar="VALUE",
        help=f"refused: {reason}" if show else argparse.SUPPRESS,
    )


def renamed(parser: argparse.ArgumentParser, old_to_new: Mapping[str, str]) -> None:
    """Old flag names, hidden, that refuse with "--old was renamed --new": no silent alias, so
    that a script learns the name that carries the unit."""
    for old, new in old_to_new.items():
        parser.add_argument(
            old,
            action=Refused,
            message=f"{old} was renamed {new}",
            dest=f"_renamed_{old.lstrip('-').replace('-', '_')}",
        )


def given(parser: argparse.ArgumentParser, args: argparse.Namespace, *dests: str) -> list[str]:
    """The flags among `dests` whose value differs from their default (were given)."""
    out = []
    for action in parser._actions:
        value = getattr(args, action.dest, action.default)
        if action.dest in dests and value != action.default:
            if isinstance(action, argparse.BooleanOptionalAction):  # the form given: --x, --no-x
                out.append(action.option_strings[0 if value else -1])
            else:
                out.append(action.option_strings[-1] if action.option_strings else action.dest)
    return out


# -- mesh and key file ----------------------------------------------------------------------------
def add_mesh_args(
    parser: argparse.ArgumentParser,
    key_file: bool = True,
    fleet_default: str | None = "covey",
    fleet_help: str = "fleet name (default: covey)",
    key_dir: bool = False,
    router: bool = False,
    mode_default: str = "peer",
    mode_help: str = "default: peer; client: of a site router, README's multi-site layout",
) -> None:
    """--fleet --connect --listen --mesh-mode --zenoh-config, and --key-file unless key_file is
    False (a CLI that signs nothing then refuses it itself, with its reason); with `key_dir`,
    --key-dir too (a process of several vehicles: one key file each, trust.auth
    .load_vehicle_auths). `router`: the process is a Zenoh router and nothing else (covey
    router): no --mesh-mode and no --fleet, which it refuses with the reason (a router carries
    every fleet's keys). `mode_default` / `mode_help`: --mesh-mode's default and why."""
    g = parser.add_argument_group("mesh")
    if router:
        parser.set_defaults(fleet="covey", mesh_mode="router")
        refuse(g, "--fleet", "a router routes every fleet's keys; members choose the fleet")
        refuse(g, "--mesh-mode", "covey router is always a Zenoh router")
    else:
        g.add_argument("--fleet", default=fleet_default, help=fleet_help)
    g.add_argument(
        "--connect",
        action="append",
        default=None,
        metavar="ENDPOINT",
        help="endpoint to connect to; repeatable or comma-separated ("
        + (
            "the other sites' routers; default: none"
            if router
            else f"default: tcp/127.0.0.1:{DEFAULT_PORT}; `covey demo` prints its own"
        )
        + ")",
    )
    if not router:
        g.add_argument(
            "--mesh-mode",
            choices=("peer", "client", "router"),
            default=mode_default,
            help=f"Zenoh role of this process ({mode_help})",
        )
    g.add_argument(
        "--listen",
        action="append",
        default=None,
        metavar="ENDPOINT",
        help="endpoint to listen on; repeatable or comma-separated (default: "
        + (
            f"tcp/127.0.0.1:{DEFAULT_PORT}; port 0: a free port, printed"
            if router
            else f"tcp/127.0.0.1:0 for a peer, tcp/127.0.0.1:{DEFAULT_PORT} for a router; "
            "a client does not listen"
        )
        + ")",
    )
    g.add_argument(
        "--zenoh-config",
        default=None,
        metavar="FILE",
        help="full Zenoh JSON5 config: TLS, user/password, access control (comms/zenoh_configs/)",
    )
    if key_file:
        g.add_argument(
            "--key-file",
            default=None,
            metavar="FILE",
            help=f"this member's key file (covey keygen add); or ${ENV_KEY_FILE}. "
            "Without one: OPEN MODE (nothing authenticated; tests only)",
        )
    if key_dir:
        g.add_argument(
            "--key-dir",
            default=None,
            metavar="DIR",
            help="a directory of member key files named vehicle-<id>.key (as covey keygen "
            "writes them), one per vehicle, each signing for its own vehicle; instead of "
            "--key-file, and the way to key several vehicles in one process",
        )


def _endpoints(items: Iterable[str] | None) -> tuple[str, ...]:
    return tuple(e.strip() for item in (items or ()) for e in item.split(",") if e.strip())


def mesh_config(
    args: argparse.Namespace, parser: argparse.ArgumentParser | None = None
) -> MeshConfig:
    """The MeshConfig the options describe. A bad combination is a one-line exit-2 error, or
    without `parser` a ValueError (MeshConfigError) that says why."""
    kw: dict[str, Any] = {"fleet": args.fleet, "mode": args.mesh_mode}
    kw["config_file"] = args.zenoh_config
    if args.connect is not None:
        kw["connect"] = _endpoints(args.connect)
    elif args.mesh_mode == "router":
        kw["connect"] = ()
    if args.listen is not None:
        if args.mesh_mode == "client":
            problem = (
                "--listen is refused for --mesh-mode client: a client accepts no links "
                "(it reaches the mesh through its router)"
            )
            if parser is None:
                raise MeshConfigError(problem)
            die(parser, problem)
        kw["listen"] = _endpoints(args.listen)
    elif args.mesh_mode == "router":
        kw["listen"] = (f"tcp/127.0.0.1:{DEFAULT_PORT}",)
    try:
        return MeshConfig(**kw)
    except ValueError as exc:
        if parser is None:
            raise
        die(parser, str(exc))


def key_file_path(args: argparse.Namespace, env: Mapping[str, str] = os.environ) -> str | None:
    """The key file the options name: --key-file, else $COVEY_FLEET_KEY_FILE, else None."""
    path = getattr(args, "key_file", None)
    return path if path is not None else env.get(ENV_KEY_FILE)


def key_env_note(
    parser: argparse.ArgumentParser, reason: str, env: Mapping[str, str] = os.environ
) -> None:
    """For a CLI that signs nothing: say so in one line when $COVEY_FLEET_KEY_FILE is set (the
    variable belongs to the shell, not to this command, so it is noted rather than refused)."""
    if env.get(ENV_KEY_FILE):
        print(f"{parser.prog}: note: ${ENV_KEY_FILE} is not used: {reason}", file=sys.stderr)


# -- stopping ---------------------------------------------------------------------------------------
@contextlib.contextmanager
def stop_on_signals(
    signals: tuple[signal.Signals, ...] = (signal.SIGINT, signal.SIGTERM),
) -> Iterator[threading.Event]:
    """An Event that SIGINT and SIGTERM set (no KeyboardInterrupt mid-shutdown); the previous
    handlers come back on exit. Off the main thread (a test calling a CLI) signals cannot be
    caught: the Event is then only set by whoever holds it."""
    stop = threading.Event()
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in signals}
    try:
        yield stop
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, signal.SIG_DFL if handler is None else handler)


@contextlib.contextmanager
def stop_after(duration_s: float | None, stop: threading.Event) -> Iterator[threading.Event]:
    """Set `stop` after `duration_s` seconds (None: never); the timer goes with the block."""
    timer = threading.Timer(duration_s, stop.set) if duration_s is not None else None
    if timer is not None:
        timer.daemon = True
        timer.start()
    try:
        yield stop
    finally:
        if timer is not None:
            timer.cancel()


# -- flags from a config dataclass ------------------------------------------------------------------
@functools.cache  # parsing the class's source is most of building a parser
def field_docs(cls: type) -> dict[str, str]:
    """The docstring under each field of a dataclass (the --help text of its flag)."""
    import ast
    import inspect
    import textwrap

    tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    body = next(n for n in tree.body if isinstance(n, ast.ClassDef)).body
    return {
        a.target.id: " ".join(b.value.value.split())
        for a, b in zip(body, body[1:], strict=False)
        if isinstance(a, ast.AnnAssign)
        and isinstance(a.target, ast.Name)
        and isinstance(b, ast.Expr)
        and isinstance(b.value, ast.Constant)
        and isinstance(b.value.value, str)
    }


def flag_name(field_name: str) -> str:
    return "--" + field_name.replace("_", "-")


def _selected(cls: type, only: Iterable[str] | None, skip: Iterable[str]) -> list:
    only, skip = (None if only is None else set(only)), set(skip)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = ((only or set()) | skip) - names
    if unknown:
        raise TypeError(f"{cls.__name__} has no fields {sorted(unknown)}")
    return [
        f
        for f in dataclasses.fields(cls)
        if f.init and (only is None or f.name in only) and f.name not in skip
    ]


def _default(f: dataclasses.Field) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return None


def add_config_flags(
    parser: argparse.ArgumentParser | argparse._ArgumentGroup,
    cls: type,
    *,
    only: Iterable[str] | None = None,
    skip: Iterable[str] = (),
    types: Mapping[str, Callable[[str], Any]] | None = None,
    flags: Mapping[str, str] | None = None,
    defaults: Mapping[str, Any] | None = None,
) -> None:
    """One flag per field of the config dataclass `cls` (those in `only`, less `skip`):
    `--field-name`, its default the field's, its help the docstring under the field.

    bool -> --name / --no-name; int, str; float -> a finite number named by the field's unit
    suffix; tuple -> a comma-separated list; `X | None` -> X, default None. `types` overrides
    the value type of a field (a range check, a unit); `flags` its flag's name (the field
    `policy_path` as `--policy`); `defaults` its default (one command's own: a wider fence)."""
    hints = typing.get_type_hints(cls)
    docs = field_docs(cls)
    for f in _selected(cls, only, skip):
        hint = hints[f.name]
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        if args and type(None) in typing.get_args(hint):
            hint = args[0]  # X | None
        base = typing.get_origin(hint) or hint
        default = defaults[f.name] if defaults and f.name in defaults else _default(f)
        text = docs.get(f.name, "").replace("%", "%%")
        kw: dict[str, Any] = {"dest": f.name, "default": default}
        if base is bool:
            kw["action"] = argparse.BooleanOptionalAction
        elif base is tuple:
            kw["type"] = comma_list
            kw["metavar"] = "A,B,..."
            text += f" (comma-separated; default: {','.join(map(str, default)) or 'none'})"
        elif base in (int, str, float):
            unit = unit_of(f.name)
            kw["type"] = {int: int, str: str, float: finite(unit or "units", minimum=None)}[base]
            if base is float and unit:
                kw["metavar"] = unit.upper()
        else:
            raise TypeError(f"{cls.__name__}.{f.name}: no flag for type {hint!r}")
        if types and f.name in types:
            kw["type"] = types[f.name]
        if base is not tuple:
            text += " (default: %(default)s)"
        name = flags[f.name] if flags and f.name in flags else flag_name(f.name)
        parser.add_argument(name, help=text.strip(), **kw)


def config_from_flags(
    cls: type,
    args: argparse.Namespace,
    *,
    only: Iterable[str] | None = None,
    skip: Iterable[str] = (),
    **overrides: Any,
) -> Any:
    """`cls` built from the flags add_config_flags added (same `only`/`skip`) and `overrides`."""
    kw = {f.name: getattr(args, f.name) for f in _selected(cls, only, skip)}
    return cls(**{**kw, **overrides})
