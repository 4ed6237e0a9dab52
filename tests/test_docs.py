"""The documentation stays true (issue 18).

1. Every `mosaic ...` / `glampoints ...` command and every `--flag` named in README.md and
   docs/*.md exists in the command-line tools' own command trees (typer's click commands).
2. docs/configuration.md lists exactly the keys of the config dataclasses (mosaic/config.py),
   each with its default.
3. Relative links and pictures resolve; CI runs the README's test command.
4. docs/layout.md names every module of mosaic/ and glampoints/; README.md stays within 150
   lines and every docs page within 400 (issue 42: reference, not diary).

Each check is a pure function of (the Markdown, the truth) returning its problems, and each is
shown to catch a fake rename, in the docs and in the code.
"""

from __future__ import annotations

import dataclasses
import math
import re
import tomllib
from pathlib import Path
from typing import Any

import pytest
import typer

REPO = Path(__file__).resolve().parents[1]
TOOLS = ("mosaic", "glampoints")
# programs whose own flags the docs may show beside ours (a segment of a command line that
# starts with one of these is not checked)
FOREIGN = ("python", "python3", "pip", "ray", "rerun", "ruff", "git", "/usr/bin/time", "cd")

Tree = dict[str, dict[str, set[str]]]  # tool -> command -> its long flags


def doc_files() -> list[Path]:
    """README.md and every docs/*.md there is (docs/reliability.md only if it exists)."""
    return [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]


def command_tree() -> Tree:
    """tool -> command -> long flags (`--x`, and `--no-x` of boolean switches), from typer."""
    from mosaic.cli import app as mosaic_app
    from mosaic.glampoints_cli import app as glampoints_app

    tree: Tree = {}
    for tool, app in (("mosaic", mosaic_app), ("glampoints", glampoints_app)):
        group = typer.main.get_command(app)  # a group (typer vendors its own click)
        assert group.commands
        tree[tool] = {
            name: {
                opt
                for param in command.params
                if param.param_type_name == "option"
                for opt in (*param.opts, *param.secondary_opts)
                if opt.startswith("--")
            }
            | {"--help"}
            for name, command in group.commands.items()
        }
    return tree


# ------------------------------------------------------------------------------------------
# 1. commands and flags
# ------------------------------------------------------------------------------------------

_FENCE = re.compile(r"^```[^\n]*\n(.*?)^```", re.S | re.M)
_SPAN = re.compile(r"`([^`\n]+)`")
_COMMAND = re.compile(r"(?<![\w./\-])(mosaic|glampoints)\s+([a-z][\w-]*)((?:\s*/\s*[a-z][\w-]*)*)")
_FLAG = re.compile(r"(?<![\w-])--[a-z][a-z0-9-]*")


def command_lines(markdown: str) -> list[str]:
    """The code of a Markdown text, as command lines: each inline code span, and each line of
    a fenced block (an indented line, or one after a trailing backslash, that does not start
    a command of its own continues the line before it)."""
    lines: list[str] = []
    for block in _FENCE.findall(markdown):
        current: str | None = None
        for raw in block.splitlines():
            stripped = raw.strip()
            if not stripped:
                current = None
                continue
            starts = stripped.split()[0] in (*TOOLS, *FOREIGN)
            continues = current is not None and (raw[:1].isspace() or current.endswith("\\"))
            if continues and not starts:
                lines[-1] = current = current.rstrip("\\") + " " + stripped
            else:
                lines.append(stripped)
                current = stripped
    outside = _FENCE.sub("", markdown)
    lines += _SPAN.findall(outside)
    return lines


def line_problems(line: str, tree: Tree) -> list[str]:
    """What `line` names that the command tree lacks: an unknown command, or a flag that its
    command (or, outside any command of ours, every command) does not have."""
    problems = []
    every_flag = {f for commands in tree.values() for flags in commands.values() for f in flags}
    found = list(_COMMAND.finditer(line))
    head = line[: found[0].start()] if found else line
    if not head.strip().startswith(FOREIGN):  # flags outside any of our commands
        for flag in _FLAG.findall(head.split("&&")[-1] if found else head):
            if flag not in every_flag:
                problems.append(f"unknown flag {flag} in `{line}`")
    for i, match in enumerate(found):
        tool = match.group(1)
        names = [match.group(2), *re.findall(r"[a-z][\w-]*", match.group(3))]
        end = found[i + 1].start() if i + 1 < len(found) else len(line)
        segment = re.split(r"&&|\|\||;", line[match.end() : end])[0]
        known: set[str] = set()
        for name in names:
            if name not in tree[tool]:
                problems.append(f"unknown command `{tool} {name}` in `{line}`")
            else:
                known |= tree[tool][name]
        if len(known) == 0:
            continue
        for flag in _FLAG.findall(segment):
            if flag not in known:
                problems.append(f"`{tool} {'/'.join(names)}` has no flag {flag}: `{line}`")
    return problems


def docs_cli_problems(texts: dict[str, str], tree: Tree) -> list[str]:
    """Every command and flag problem of the given Markdown texts (name -> text)."""
    return [
        f"{name}: {problem}"
        for name, text in texts.items()
        for line in command_lines(text)
        for problem in line_problems(line, tree)
    ]


def _texts() -> dict[str, str]:
    return {str(p.relative_to(REPO)): p.read_text(encoding="utf-8") for p in doc_files()}


def test_every_command_and_flag_in_the_docs_exists():
    texts = _texts()
    assert "docs/configuration.md" in texts and "README.md" in texts
    lines = [line for text in texts.values() for line in command_lines(text)]
    assert sum(bool(_COMMAND.search(line)) for line in lines) > 30  # the parser finds them
    assert docs_cli_problems(texts, command_tree()) == []


def test_the_cli_check_catches_a_renamed_flag_or_command():
    texts, tree = _texts(), command_tree()
    assert "`mosaic build VIDEO -o mosaic.png" in texts["README.md"]
    assert "[--max-frames N]" in texts["docs/commands.md"]
    # a flag renamed in the code: every place the docs name it is reported
    renamed = {tool: {c: set(f) for c, f in cmds.items()} for tool, cmds in tree.items()}
    renamed["mosaic"]["build"] = {
        "--max-frame" if f == "--max-frames" else f for f in tree["mosaic"]["build"]
    }
    problems = docs_cli_problems(texts, renamed)
    assert any(
        p.startswith("docs/commands.md: `mosaic build` has no flag --max-frames") for p in problems
    ), problems
    # a command renamed in the code: the README's table and the quick start are reported
    renamed["mosaic"]["assemble"] = renamed["mosaic"].pop("build")
    problems = docs_cli_problems(texts, renamed)
    assert any(p.startswith("README.md: unknown command `mosaic build`") for p in problems), (
        problems
    )
    # a flag and a command misspelt in the docs
    fake = {"fake.md": "Run `mosaic build v.mp4 --max-frame 5`, or\n\n```\nmosaic mosaik x\n```\n"}
    problems = docs_cli_problems(fake, tree)
    assert any("no flag --max-frame" in p for p in problems), problems
    assert any("unknown command `mosaic mosaik`" in p for p in problems), problems
    # a flag on a continuation line of a fenced block belongs to the command above it
    fake = {"fake.md": "```\nmosaic batch in/ -o out/\n      [--workers N] [--wrokers N]\n```\n"}
    assert docs_cli_problems(fake, tree) == [
        "fake.md: `mosaic batch` has no flag --wrokers: "
        "`mosaic batch in/ -o out/ [--workers N] [--wrokers N]`"
    ]
    # a flag with no command beside it must be some command's flag; other programs' are not ours
    fake = {"fake.md": "`--strategy chain`, `--stratgey`, `ray start --head`, `pip install -e .`"}
    assert docs_cli_problems(fake, tree) == ["fake.md: unknown flag --stratgey in `--stratgey`"]


# ------------------------------------------------------------------------------------------
# 2. configuration keys
# ------------------------------------------------------------------------------------------

_TABLE_HEADING = re.compile(r"^#+\s.*?`?\[(\w+)\]`?", re.M)
_KEY_ROW = re.compile(r"^\|\s*`(\w+)`\s*\|\s*`([^`]*)`\s*\|", re.M)


def config_defaults() -> dict[str, Any]:
    """`table.key` -> default, walking the dataclasses of mosaic/config.py."""
    from mosaic.config import Config

    out = {}
    for table in dataclasses.fields(Config):
        for key in dataclasses.fields(table.default_factory()):
            out[f"{table.name}.{key.name}"] = getattr(table.default_factory(), key.name)
    return out


def documented_keys(markdown: str) -> dict[str, str]:
    """`table.key` -> the default as written (TOML), from configuration.md: a heading naming
    `[table]` starts a table's section, and each row `| `key` | `default` | ... |` is a key."""
    out: dict[str, str] = {}
    headings = list(_TABLE_HEADING.finditer(markdown))
    for i, heading in enumerate(headings):
        end = headings[i + 1].start() if i + 1 < len(headings) else len(markdown)
        for key, default in _KEY_ROW.findall(markdown[heading.end() : end]):
            name = f"{heading.group(1)}.{key}"
            assert name not in out, f"{name} listed twice"
            out[name] = default
    return out


def _same(written: str, value: Any) -> bool:
    try:
        parsed = tomllib.loads(f"v = {written}")["v"]
    except tomllib.TOMLDecodeError:
        return False
    if isinstance(value, bool) or isinstance(parsed, bool):
        return type(parsed) is type(value) and parsed == value
    if isinstance(value, float):
        return isinstance(parsed, int | float) and math.isclose(parsed, value)
    return type(parsed) is type(value) and parsed == value


def config_doc_problems(documented: dict[str, str], defaults: dict[str, Any]) -> list[str]:
    """Keys missing from the page, keys the code lacks, and wrong defaults."""
    problems = [f"not documented: {k}" for k in defaults if k not in documented]
    problems += [f"documented but not a config key: {k}" for k in documented if k not in defaults]
    problems += [
        f"{k}: documented default {documented[k]} but the code's is {defaults[k]!r}"
        for k in defaults
        if k in documented and not _same(documented[k], defaults[k])
    ]
    return problems


def _configuration_md() -> str:
    return (REPO / "docs" / "configuration.md").read_text(encoding="utf-8")


def test_configuration_md_lists_exactly_the_config_keys_with_their_defaults():
    documented, defaults = documented_keys(_configuration_md()), config_defaults()
    assert len(defaults) > 50
    assert config_doc_problems(documented, defaults) == []


def test_the_config_check_catches_a_renamed_key_or_a_changed_default():
    documented, defaults = documented_keys(_configuration_md()), config_defaults()
    before = set(config_doc_problems(documented, defaults))  # none, once the page is up to date

    def new_problems(documented: dict[str, str], defaults: dict[str, Any]) -> list[str]:
        return sorted(set(config_doc_problems(documented, defaults)) - before)

    # a key renamed in the code (as a new field would be: missing from the page)
    renamed = {
        ("pipeline.strategy_name" if k == "pipeline.strategy" else k): v
        for k, v in defaults.items()
    }
    assert new_problems(documented, renamed) == [
        "documented but not a config key: pipeline.strategy",
        "not documented: pipeline.strategy_name",
    ]
    # a key renamed in the page, in the Markdown itself
    text = _configuration_md().replace("| `max_side_px` |", "| `max_side` |")
    assert new_problems(documented_keys(text), defaults) == [
        "documented but not a config key: preprocess.max_side",
        "not documented: preprocess.max_side_px",
    ]
    # a default changed in the code
    changed = {**defaults, "compose.blend": "feather", "registration.min_inliers": 21}
    assert new_problems(documented, changed) == [
        "compose.blend: documented default \"multiband\" but the code's is 'feather'",
        "registration.min_inliers: documented default 20 but the code's is 21",
    ]


@pytest.mark.parametrize(
    "written,value,same",
    [
        ("true", True, True),
        ("1", True, False),
        ("0.01", 0.01, True),
        ("8000", 8000, True),
        ('"auto"', "auto", True),
        ("auto", "auto", False),
        ("0", 0.0, True),
        ("1.0", 1, False),
    ],
)
def test_defaults_compare_as_toml_values(written, value, same):
    assert _same(written, value) is same


# ------------------------------------------------------------------------------------------
# 3. links and pictures
# ------------------------------------------------------------------------------------------

_LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")


def _slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces as hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def test_relative_links_and_pictures_resolve():
    problems = []
    for path in doc_files():
        for target in _LINK.findall(path.read_text(encoding="utf-8")):
            if re.match(r"[a-z]+:", target):
                continue  # a web address
            file, _, anchor = target.partition("#")
            resolved = (path.parent / file).resolve() if file else path
            if resolved == REPO / "docs" / "reliability.md" and not resolved.exists():
                continue  # written alongside, by the reliability work (issue 15)
            if not resolved.exists():
                problems.append(f"{path.name}: {target} does not exist")
            elif anchor and resolved.suffix == ".md":
                headings = re.findall(r"^#+ (.*)$", resolved.read_text(encoding="utf-8"), re.M)
                if anchor not in {_slug(h) for h in headings}:
                    problems.append(f"{path.name}: no heading #{anchor} in {file or path.name}")
    assert problems == []
    pictures = sorted((REPO / "docs" / "img").glob("*.jpg"))
    assert pictures and all(p.stat().st_size < 200_000 for p in pictures)


def test_ci_runs_the_readme_test_command_and_it_runs_every_test():
    """`.ci/run` runs the README's test command, word for word, and that command runs the
    tests marked slow too (the plain `pytest` of the fast run leaves them out)."""
    readme = (REPO / "README.md").read_text(encoding="utf-8")
    commands = [line for line in readme.splitlines() if "pip install -q -e '.[test]'" in line]
    assert len(commands) == 1, commands
    assert commands[0] in (REPO / ".ci" / "run").read_text(encoding="utf-8")
    assert '-m "slow or not slow"' in commands[0]


# ------------------------------------------------------------------------------------------
# 4. layout and length (issue 42: docs as reference, not diary)
# ------------------------------------------------------------------------------------------

README_MAX_LINES = 150
DOC_MAX_LINES = 400
# pages over DOC_MAX_LINES that are known and owed a trim (name -> why); empty when none
LONG_PAGES: dict[str, str] = {}


def package_modules() -> list[str]:
    """`package/module.py` of every public module of mosaic/ and glampoints/ (not __init__,
    not private `_*.py`), subpackages included."""
    return sorted(
        str(path.relative_to(REPO))
        for package in ("mosaic", "glampoints")
        for path in (REPO / package).rglob("*.py")
        if not path.name.startswith("_")
    )


def unnamed_modules(layout: str, modules: list[str]) -> list[str]:
    """The modules whose name layout.md does not give as code (`name`, or `sub/name`)."""
    named = set(_SPAN.findall(layout))
    missing = []
    for module in modules:
        parts = module.removesuffix(".py").split("/")
        names = {parts[-1], "/".join(parts[1:]), ".".join(parts[1:]), ".".join(parts)}
        if not names & named:
            missing.append(module)
    return missing


def test_layout_md_names_every_module():
    layout = (REPO / "docs" / "layout.md").read_text(encoding="utf-8")
    modules = package_modules()
    assert "mosaic/pipeline.py" in modules and "glampoints/nms.py" in modules
    assert unnamed_modules(layout, modules) == []
    # the check catches a module the page leaves out
    assert unnamed_modules(layout.replace("`allocator`", "allocator"), modules) == [
        "mosaic/allocator.py"
    ]


def test_readme_and_docs_pages_are_short():
    readme = (REPO / "README.md").read_text(encoding="utf-8").splitlines()
    assert len(readme) <= README_MAX_LINES
    long = {
        path.name: n
        for path in sorted((REPO / "docs").glob("*.md"))
        if (n := len(path.read_text(encoding="utf-8").splitlines())) > DOC_MAX_LINES
    }
    assert set(long) == set(LONG_PAGES), long
