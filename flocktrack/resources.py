"""What the package ships besides code: the Zenoh router configs and the bundled scenarios.

Both are package data of ``flocktrack`` (``flocktrack/data/broker_cfg/`` and ``flocktrack/data/scenarios/``;
in a source checkout these two are links to the top-level ``broker_cfg/`` and ``scenarios/``, which are
the files themselves) and are found through :mod:`importlib.resources`, so an installed wheel runs from
any directory.

    broker_config("local.json5")          the embedded router's config (a Path)
    config_file(arg)                      a --config argument: a file as given, else a shipped config
    scenario_names()                      ["carrillo_robust", …, "demo", …]
    scenario_description("demo")          the first line of its opening comment
    resolve_scenario("demo")              a path as given, else a bundled scenario's file (a str)

A command-line argument that names a scenario goes through :func:`resolve_scenario`: a file that
exists is taken as it is; otherwise ``NAME``, ``NAME.toml`` or ``scenarios/NAME.toml`` name a bundled
scenario. Anything else is :class:`UnknownScenarioError`, whose message lists the bundled names.
"""

from __future__ import annotations

import os
from importlib import resources
from pathlib import Path

CONFIG_DIR = "broker_cfg"
SCENARIO_DIR = "scenarios"
REINSTALL = "pip install --force-reinstall flocktrack"


class MissingDataError(RuntimeError):
    """A file the package should hold is not there: the install is broken."""


class UnknownScenarioError(ValueError):
    """A scenario argument that is neither a file nor a bundled scenario's name."""


def _data_dir(kind: str) -> Path:
    root = resources.files("flocktrack").joinpath("data", kind)
    try:
        path = Path(os.fspath(root))
    except TypeError:   # a Traversable that is no file system path (a zipped install)
        raise MissingDataError(f"flocktrack's {kind}/ is not on the file system ({root!r}); install the package "
                               f"unzipped: {REINSTALL}") from None
    if not path.is_dir():
        raise MissingDataError(f"flocktrack's package data {kind}/ is missing ({path}): the install is broken; "
                               f"{REINSTALL}")
    return path


def broker_config(name: str) -> Path:
    """The router/client config ``broker_cfg/<name>`` that the package ships (``local.json5``,
    ``secure.json5``, ``compose_router.json5``, ``mesh/router.json5`` …)."""
    path = _data_dir(CONFIG_DIR) / name
    if not path.is_file():
        raise MissingDataError(f"flocktrack's package data {CONFIG_DIR}/{name} is missing: the install is broken; "
                               f"{REINSTALL}")
    return path


def config_file(arg: str | Path) -> Path:
    """``arg`` if it is a file, else the package's config of that name (``compose_router.json5``,
    ``mesh/client.json5``): what a ``--config`` option takes. Neither: :class:`FileNotFoundError`
    whose message lists the shipped configs."""
    if Path(arg).is_file():
        return Path(arg)
    root = _data_dir(CONFIG_DIR)
    if (root / str(arg)).is_file():
        return root / str(arg)
    shipped = sorted(p.relative_to(root).as_posix() for p in root.rglob("*.json5"))
    raise FileNotFoundError(f"no config file {str(arg)!r}, and the package ships none of that name "
                            f"(it ships: {', '.join(shipped)})")


def scenario_dir() -> Path:
    """The directory of the bundled scenarios."""
    return _data_dir(SCENARIO_DIR)


def scenario_names() -> list[str]:
    """The bundled scenarios' names (file names without ``.toml``), sorted."""
    return sorted(p.stem for p in scenario_dir().glob("*.toml"))


def scenario_file(name: str) -> Path:
    """The file of the bundled scenario ``name`` (:class:`UnknownScenarioError` if there is none)."""
    path = scenario_dir() / f"{name}.toml"
    if not path.is_file():
        raise UnknownScenarioError(_unknown(name))
    return path


def scenario_description(name: str) -> str:
    """The first line of the bundled scenario's opening comment: what it shows, in one line."""
    for line in scenario_file(name).read_text(encoding="utf-8").splitlines():
        text = line.strip()
        if not text:
            continue
        return text.lstrip("#").strip() if text.startswith("#") else ""
    return ""


def bundled_name(path: str | Path) -> str | None:
    """The name of the bundled scenario that ``path`` is (the same file), else None."""
    try:
        p = Path(path).resolve()
        return p.stem if p.parent == scenario_dir().resolve() and p.suffix == ".toml" else None
    except (OSError, MissingDataError):
        return None


def resolve_scenario(arg: str) -> str:
    """``arg`` if it is a file; else the path of the bundled scenario it names (``NAME``, ``NAME.toml``,
    ``scenarios/NAME.toml``); else :class:`UnknownScenarioError`."""
    p = Path(arg)
    if p.is_file():
        return arg
    name = p.stem if p.suffix in ("", ".toml") and p.parent.as_posix() in (".", SCENARIO_DIR) else None
    if name and (scenario_dir() / f"{name}.toml").is_file():
        return str(scenario_dir() / f"{name}.toml")
    raise UnknownScenarioError(_unknown(arg))


def scenario_arg(text: str) -> str:
    """The argparse ``type`` of a SCENARIO argument: :func:`resolve_scenario`, its error as argparse's."""
    import argparse

    try:
        return resolve_scenario(text)
    except (UnknownScenarioError, MissingDataError) as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def add_scenario_argument(parser) -> None:
    """The positional SCENARIO of a sub-command: a file, or a bundled scenario's name (:func:`scenario_arg`)."""
    parser.add_argument("scenario", type=scenario_arg, help="a scenario file, or the name of a bundled one")


def _unknown(arg: str) -> str:
    from agent.suggest import did_you_mean

    names = scenario_names()
    hint = did_you_mean(Path(arg).stem, names, quote="'")
    return (f"no scenario file {arg!r} and no bundled scenario of that name; {hint}bundled: {', '.join(names)} "
            f"(`flocktrack scenarios` describes them); a path to a .toml file works too")


def load_json5(path: str | Path) -> dict:
    """A JSON5 config (a file, or the name of one in the package's ``broker_cfg/``) as a dict."""
    import json5

    return json5.loads(config_file(path).read_text(encoding="utf-8"))
