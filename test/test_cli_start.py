"""``pws --help`` starts at once (issue 34): it imports no command module and nothing heavy (torch, numpy,
scipy), yet lists every command with the one line its own ``--help`` registers; ``pws COMMAND --help``
builds that command's parser in full."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
HEAVY = ("torch", "numpy", "scipy", "yaml", "rosbags", "ray")


def _imported_by(args: list[str]) -> tuple[str, set[str]]:
    """(stdout, top-level modules imported) of ``python -X importtime -m pws_ros.cli ARGS`` in a fresh interpreter."""
    out = subprocess.run([sys.executable, "-X", "importtime", "-m", "pws_ros.cli", *args], cwd=ROOT, capture_output=True,
                         text=True, timeout=120, env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"})
    names = {line.split("|")[-1].strip().split(".")[0] for line in out.stderr.splitlines() if line.startswith("import time:")}
    full = {line.split("|")[-1].strip() for line in out.stderr.splitlines() if line.startswith("import time:")}
    return out.stdout, names | full


def test_pws_help_imports_nothing_heavy():
    from pws_ros.commands import SUMMARIES

    stdout, modules = _imported_by(["--help"])
    assert not modules & set(HEAVY), sorted(modules & set(HEAVY))
    assert not any(m.startswith("pws_ros.commands.") or m.startswith("pws_ros.core.") and m != "pws_ros.core.errors"
                   for m in modules), sorted(m for m in modules if m.startswith("pws_ros."))
    for name in SUMMARIES:
        assert f"\n    {name}" in stdout


def test_a_certification_imports_neither_scipy_stats_nor_sympy():
    """A command's start before its first frame (issue 34, item 3): scipy.stats (about a second: the statistics come
    from scipy.special, the same values) and sympy (half a second: torch's symbolic shapes, which
    torch.broadcast_shapes imports on first use) are not imported by a whole certification, bag reading included."""
    stdout, modules = _imported_by(["ceiling", str(ROOT / "bags" / "demo"), "--no-model", "--max-frames", "1", "--axes", "tz",
                                    "--size", "30x40"])
    assert "median ceiling" in stdout, stdout
    assert "torch" in modules and "rosbags" in modules     # (the check sees the imports of a certification)
    assert not modules & {"scipy.stats", "sympy"}, sorted(modules & {"scipy.stats", "sympy"})


def test_the_listed_lines_are_the_commands_own():
    """The lines `pws --help` lists without importing a command are the help each command registers."""
    import argparse

    from pws_ros.cli import build_parser
    from pws_ros.commands import SUMMARIES

    def listed(parser: argparse.ArgumentParser) -> dict[str, str]:
        sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        return {a.dest: a.help for a in sub._choices_actions}

    assert listed(build_parser()) == listed(build_parser(None)) == SUMMARIES


def test_a_command_help_is_built_in_full(capsys):
    import pytest

    from pws_ros import cli

    with pytest.raises(SystemExit) as exc:
        cli.main(["plan", "--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: pws plan") and "--radius" in out and "--method" in out


def test_ctrl_c_while_the_command_loads_is_a_clean_exit_130(monkeypatch, capsys):
    """SIGINT in the first second (numpy and torch loading while the parser is built) ends with one line and 130, no
    traceback."""
    import pws_ros.cli as cli

    def interrupted(_command):
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "build_parser", interrupted)
    assert cli.main(["replay", "bags/demo"]) == 130
    assert capsys.readouterr().err == "pws replay: interrupted\n"


def test_every_command_and_option_explains_itself():
    """`pws COMMAND [SUB] --help` of every command and subcommand opens with a description, and every option
    has a help text (the README says each command's help is complete)."""
    import argparse

    from pws_ros.cli import build_parser

    missing = []

    def walk(parser: argparse.ArgumentParser, name: str) -> None:
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for sub_name, sub in action.choices.items():
                    if not (sub.description or "").strip():
                        missing.append(f"{name} {sub_name}: no description")
                    walk(sub, f"{name} {sub_name}")
            elif not isinstance(action, (argparse._HelpAction, argparse._VersionAction)) and not (action.help or "").strip():
                missing.append(f"{name} {'/'.join(action.option_strings) or action.dest}: no help")

    walk(build_parser("*"), "pws")
    assert not missing, missing
