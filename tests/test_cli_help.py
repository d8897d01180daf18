"""The command line reads well: ``--help`` in plain text (the docstrings' RST and the README's
Markdown stay out of the terminal), a help string on every option and its default where it has
one; and ``summary.json`` gives the parameters as the user gave them, not as float32 noise."""

from __future__ import annotations

import argparse
import json
import re

import numpy as np
import pytest

from jaxslam.cli import make_parser
from jaxslam.config import default_params, params_to_dict
from jaxslam.outputs import as_given, summary_params

MARKUP = re.compile(r"`|\*\*|:(?:class|func|meth|mod|data|attr|ref|doc|obj):")
"""RST and Markdown in help text: backticks (single, double: code and roles), ``**`` (bold),
and Sphinx roles even without their backticks."""


def _parsers() -> dict[str, argparse.ArgumentParser]:
    """``jaxslam`` and each of its commands by name, found from the parser (a new command is
    checked without being listed here)."""
    top = make_parser()
    commands = next(a for a in top._actions if isinstance(a, argparse._SubParsersAction)).choices
    return {"jaxslam": top, **{f"jaxslam {name}": parser for name, parser in commands.items()}}


PARSERS = _parsers()


def test_every_command_is_checked():
    assert {"jaxslam map", "jaxslam demo", "jaxslam eval", "jaxslam diagnose", "jaxslam doors"} <= set(PARSERS)


@pytest.mark.parametrize("name", sorted(PARSERS))
def test_help_has_no_markup(name):
    text = PARSERS[name].format_help()
    found = sorted({m.group(0) for m in MARKUP.finditer(text)})
    lines = [line.strip() for line in text.splitlines() if MARKUP.search(line)]
    assert not found, f"{name} --help shows markup {found}: {lines}"


def _help_of(parser: argparse.ArgumentParser, action: argparse.Action) -> str:
    """``action``'s help as ``--help`` prints it (``%(default)s`` filled in), on one line."""
    return " ".join(parser._get_formatter()._expand_help(action).split())


@pytest.mark.parametrize("name", sorted(PARSERS))
def test_every_option_has_help_and_its_default(name):
    parser = PARSERS[name]
    for action in parser._actions:
        if isinstance(action, argparse._HelpAction):
            continue
        label = "/".join(action.option_strings) or action.dest
        assert action.help and action.help is not argparse.SUPPRESS, f"{name} {label} has no help"
        text = _help_of(parser, action)
        assert text.strip(), f"{name} {label} has no help"
        if action.default in (None, False, argparse.SUPPRESS) or not action.option_strings:
            continue  # nothing to show: the option is off or unset unless given
        assert "default" in text, f"{name} {label}: its default {action.default!r} is not shown: {text}"
        if not isinstance(action.default, bool):  # a flag's default reads as its name (default: refine)
            assert str(action.default) in text, f"{name} {label}: default {action.default!r} not in {text!r}"


def test_the_top_level_help_lists_every_command_in_plain_words():
    text = " ".join(PARSERS["jaxslam"].format_help().split())
    for command in ("map", "demo", "eval", "diagnose", "doors"):
        assert f" {command} " in text, command
    assert "--set NAME=VALUE" in text and "exit code 2" in text


def test_a_float32_parameter_is_written_as_given():
    """0.1 held as float32 reads back as 0.10000000149011612; the summary writes 0.1."""
    params = default_params(**{"motion.srr": 0.1, "likelihood.sigma": 0.07})
    assert params_to_dict(params)["motion.srr"] != 0.1  # the noise this is about
    written = summary_params(params)
    assert set(written) == set(params_to_dict(params))  # every key kept
    assert written["motion.srr"] == 0.1 and written["likelihood.sigma"] == 0.07
    assert '"motion.srr": 0.1,' in json.dumps(written)
    assert all(type(v) is float for v in written.values())


def test_as_given_changes_only_float32_noise():
    assert as_given(float(np.float32(3e-9))) == 3e-9 and as_given(np.float32(0.25)) == 0.25
    assert as_given(0.1 + 1e-12) == 0.1 + 1e-12  # a float64 no float32 holds: every digit kept
    for value in (True, False, 3, "scan_match", None):
        assert as_given(value) is value
    assert np.isnan(as_given(float("nan"))) and as_given(float("-inf")) == float("-inf")
