"""The documentation stays in step with the code, without building the site (``make docs``).

- the command reference's directive targets the real parser, and what sphinx-argparse renders
  from it lists every subcommand ``tetdose --help`` lists and every option of each;
- the API reference lists every public name of ``tetdose`` and of its packages;
- every README section went to a page: each page the README links to exists;
- the docstring examples (doctests) of the public names run.
"""

import doctest
import importlib
import re
from pathlib import Path

import pytest

import tetdose
from tetdose.cli import build_parser, main

ROOT = Path(__file__).resolve().parents[2]
DOCS = ROOT / "docs"


def _help_subcommands(capsys) -> list[str]:
    try:
        assert main(["--help"]) == 0
    except SystemExit as exc:  # argparse's own exit, if main lets it through
        assert exc.code == 0
    out = capsys.readouterr().out
    return re.findall(r"^    ([a-z0-9][a-z0-9-]*)(?:\s|$)", out, flags=re.M)


def test_command_reference_targets_the_real_parser():
    text = (DOCS / "cli.md").read_text()
    module = re.search(r":module:\s*(\S+)", text).group(1)
    func = re.search(r":func:\s*(\S+)", text).group(1)
    assert getattr(importlib.import_module(module), func) is build_parser


def test_command_reference_lists_every_subcommand_and_option(capsys):
    parser_mod = pytest.importorskip("sphinxarg.parser")
    rendered = parser_mod.parse_parser(build_parser())
    commands = {c["name"]: c for c in rendered["children"]}
    assert sorted(commands) == sorted(_help_subcommands(capsys))
    for name, sub in build_parser()._subparsers._group_actions[0].choices.items():  # noqa: SLF001
        shown = {s for group in commands[name]["action_groups"] for opt in group["options"]
                 for s in opt["name"]}
        wanted = {s for a in sub._actions for s in (a.option_strings or [a.dest])  # noqa: SLF001
                  if s not in ("-h", "--help")}
        assert wanted <= shown, (name, wanted - shown)


def test_api_reference_lists_every_public_name():
    text = (DOCS / "api.rst").read_text()
    listed = set(re.findall(r"^   (\w+)$", text, flags=re.M))
    listed |= set(re.findall(r":obj:`tetdose\.(\w+)`", text))
    assert set(tetdose.__all__) - {"__version__", "phantoms"} <= listed
    for package in re.findall(r"^\.\. automodule:: (tetdose\.\w+)$", text, flags=re.M):
        names = getattr(importlib.import_module(package), "__all__", [])
        assert set(names) <= listed, (package, set(names) - listed)


def test_readme_links_to_every_page():
    readme = (ROOT / "README.md").read_text()
    links = set(re.findall(r"\]\(((?:docs|examples|bench)/[^)#]*)\)", readme))
    for link in links:
        assert (ROOT / link).exists(), link
    pages = {p.relative_to(ROOT).as_posix() for p in DOCS.rglob("*.md") if "_build" not in p.parts}
    assert pages | {"docs/api.rst", "examples/"} <= links | {"docs/index.md"}
    assert len(readme.splitlines()) <= 200


@pytest.mark.parametrize("name", ["tetdose.core.calibration", "tetdose.core.image"])
def test_docstring_examples(name):
    failed, tried = doctest.testmod(importlib.import_module(name), optionflags=doctest.ELLIPSIS)
    assert tried and not failed
