"""The docs stay true: every command they show parses, every path, test and section they cite
exists, every run option is documented where a user looks, and no removed option is named.

Everything here reads files and the command objects typer builds (its own copy of click): no
subprocess, no run, the fast suite.
"""

from __future__ import annotations

import ast
import importlib
import re
import shlex
from functools import cache
from pathlib import Path

import pytest
import typer
from typer._click.core import Command
from typer._click.exceptions import UsageError

ROOT = Path(__file__).resolve().parents[1]
DOCS = sorted([ROOT / "README.md", ROOT / "deploy" / "experiments" / "README.md", *(ROOT / "docs").glob("*.md")])
# Code that cites doc sections (a comment or message saying `docs/X.md, "Section"`).
CODE = sorted(p for d in ("mam_core", "mam_lab", "services", "tests", "benchmarks")
              for p in (ROOT / d).rglob("*") if p.suffix in (".py", ".sh") and p.name != "test_docs.py")

# -- reading the docs ------------------------------------------------------------------------------
FENCE = re.compile(r"^```([\w-]*)\n(.*?)^```", re.S | re.M)
SPAN = re.compile(r"(?<!`)`([^`\n]+)`(?!`)")


def _text(path: Path) -> str:
    return path.read_text(encoding="utf-8")


def _prose(text: str) -> str:
    """The text outside fenced blocks."""
    return FENCE.sub("", text)


def shell_lines(path: Path) -> list[str]:
    """The command lines of a doc's shell blocks (```bash, ```sh or a bare ```), comments cut,
    `\\` continuations joined."""
    lines: list[str] = []
    for lang, body in FENCE.findall(_text(path)):
        if lang not in ("bash", "sh", "shell", "console", ""):
            continue
        body = re.sub(r"\\\n\s*", " ", body)
        lines += [ln.split(" #")[0].strip() for ln in body.splitlines() if not ln.lstrip().startswith("#")]
    return [ln for ln in lines if ln]


def inline_spans(path: Path) -> list[str]:
    return SPAN.findall(_prose(_text(path)))


# -- the command objects ---------------------------------------------------------------------------
ROLES = ("learner", "worker", "referee", "monitor")


def _click(app: typer.Typer) -> Command:
    return typer.main.get_command(app)


def _typer_of(module: str, function: str) -> Command:
    from services.run import options

    sub = typer.Typer(add_completion=False)
    sub.command(cls=options.PlainFlags)(getattr(importlib.import_module(module), function))
    return _click(sub)


@cache
def commands() -> dict[str, Command]:
    """`mam X` and `mam-X` by the words a doc writes, each the click command that parses its flags
    (the pass-through subcommands of `mam` resolved to the command they hand their arguments to)."""
    from services.cli.app import app

    top = _click(app)
    found: dict[str, Command] = {"mam": top}
    for name, cmd in top.commands.items():  # type: ignore[attr-defined]
        found[f"mam {name}"] = cmd
    for role in ROLES:
        role_cmd = _click(importlib.import_module(f"services.roles.{role}").app)
        found[f"mam-{role}"] = role_cmd
        if role != "monitor":
            found[f"mam {role}"] = role_cmd
    found["mam router"] = _click(importlib.import_module("services.roles.router").app)
    found["mam bench"] = _click(importlib.import_module("mam_lab.bench").app)
    found["mam chaos"] = _click(importlib.import_module("services.run.chaos").app)
    found["mam experiment"] = _typer_of("mam_lab.experiment", "experiment_command")
    found["mam report"] = _typer_of("mam_lab.report", "report_command")
    return found


def flags_of(cmd: Command) -> set[str]:
    names = {"--help"}
    for p in cmd.params:
        names.update(o for o in (*p.opts, *p.secondary_opts) if o.startswith("--"))
    return names


COMMAND = re.compile(r"(?:^|(?<=[\s(;&|]))(?:\.venv/bin/)?(mam(?:-(?:learner|worker|referee|monitor))?)(?=\s|$)(.*)")
FLAG = re.compile(r"(?<![\w-])--[a-z][a-z0-9-]*")


def command_mentions() -> list[tuple[str, str, str]]:
    """(doc, command words, the rest of the mention) for every `mam …` / `mam-… …` a doc shows,
    in a shell block or an inline code span."""
    found = []
    for path in DOCS:
        name = path.relative_to(ROOT).as_posix()
        for text in (*shell_lines(path), *inline_spans(path)):
            for part in re.split(r"\s*(?:&&|\|\||;|\|)\s*", text):
                m = COMMAND.match(part.strip())
                if not m:
                    continue
                exe, rest = m.group(1), m.group(2).strip()
                words = exe
                sub = rest.split()[0] if rest.split() else ""
                if exe == "mam" and re.fullmatch(r"[a-z]+", sub):
                    words, rest = f"mam {sub}", rest[len(sub):].strip()
                found.append((name, words, rest))
    for unit in sorted((ROOT / "deploy" / "systemd").glob("*.service")):  # the units' commands too
        for line in re.findall(r"^ExecStart=\S*/bin/(.*)$", _text(unit), re.M):
            exe, _, rest = line.partition(" ")
            sub = rest.split()[0] if exe == "mam" else ""
            words = f"mam {sub}" if sub else exe
            found.append((unit.relative_to(ROOT).as_posix(), words, rest[len(sub):].strip()))
    return found


def test_the_docs_show_commands():
    """The collector finds what the README shows (a guard: an empty list would pass everything)."""
    words = {w for _, w, _ in command_mentions()}
    assert {"mam run", "mam watch", "mam eval", "mam experiment", "mam report", "mam-worker", "mam-learner",
            "mam router", "mam-referee"} <= words
    assert any(doc.endswith(".service") for doc, _, _ in command_mentions())


def test_every_documented_command_and_flag_exists():
    bad = []
    known = commands()
    for doc, words, rest in command_mentions():
        cmd = known.get(words)
        if cmd is None:
            bad.append(f"{doc}: `{words}` is no command")
            continue
        allowed = flags_of(cmd)
        if words == "mam chaos":  # it passes the flags it does not know to `mam run`
            allowed |= flags_of(known["mam run"])
        if words in ("mam", "mam bench", "mam chaos", "mam experiment", "mam report") or cmd.params:
            for flag in FLAG.findall(rest):
                if flag not in allowed:
                    bad.append(f"{doc}: `{words} {rest}`: {flag} is not in `{words} --help`")
    assert not bad, "\n".join(bad)


def _placeholder(token: str) -> bool:
    return bool(re.search(r"[A-Z_]{2,}|<|…|\.\.\.|\$|\[|\{|\|", token))


def test_every_documented_command_line_parses():
    """A shell block's `mam` line is meant to be pasted: the parser parses it (options, their values,
    the arguments) without running it."""
    bad = []
    known = commands()
    for path in DOCS:
        doc = path.relative_to(ROOT).as_posix()
        for line in shell_lines(path):
            m = COMMAND.match(line)
            if not m or "…" in line or "..." in line:
                continue
            words = shlex.split(m.group(1) + " " + m.group(2))
            name = words[0]
            if name == "mam" and len(words) > 1 and f"mam {words[1]}" in known:
                name, words = f"mam {words[1]}", words[1:]
            cmd = known.get(name)
            if cmd is None or name in ("mam chaos", "mam bench"):
                continue
            try:
                cmd.make_context(name, list(words[1:]), resilient_parsing=True)
            except UsageError as e:
                bad.append(f"{doc}: `{line}`: {e.format_message()}")
    assert not bad, "\n".join(bad)


# -- paths, tests, modules and sections ------------------------------------------------------------
TOP = ("mam_core", "mam_lab", "services", "tests", "deploy", "docs", "benchmarks")
PATH = re.compile(r"(?<![\w./-])((?:" + "|".join(TOP) + r")/[A-Za-z0-9_.*/<>{}@-]*[A-Za-z0-9_*>}])(::\w+)?")
DOTTED = re.compile(r"(?<![\w./-])((?:mam_core|mam_lab|services)(?:\.\w+)+)")


def _cited(texts: dict[str, str]):
    for doc, text in texts.items():
        for m in PATH.finditer(text):
            yield doc, m.group(1), (m.group(2) or "")[2:]


def _doc_texts() -> dict[str, str]:
    return {p.relative_to(ROOT).as_posix(): _text(p) for p in DOCS}


IGNORED = tuple(line.strip("/") for line in (ROOT / ".gitignore").read_text().splitlines() if "/" in line.strip("/"))
PLACEHOLDER = re.compile(r"[<{]|\b[A-Z]+\b(?!\.md)")  # `docs/results/<name>`, `evidence-X.toml`, `NAME/`


def _path_exists(cited: str) -> bool:
    if (ROOT / cited).exists() or cited.startswith(IGNORED):  # an ignored folder is made by a command
        return True
    if "*" in cited:
        return any(ROOT.glob(cited))
    parts = cited.split("/")
    for i, part in enumerate(parts):
        if PLACEHOLDER.search(part):  # the fixed head of a placeholder path exists
            return (ROOT / "/".join(parts[:i])).is_dir()
    module = cited.split(".")[0] + ".py"  # `benchmarks/td3_reference.TD3.train`
    return "." in cited and (ROOT / module).is_file()


def test_every_cited_path_exists():
    bad = [f"{doc}: {cited}" for doc, cited, _ in _cited(_doc_texts()) if not _path_exists(cited)]
    assert not bad, "\n".join(bad)


OTHER_PROJECTS_FILES = {"pyproject.toml", "main.py"}  # main.py: sfujim/TD3's training loop (PERFORMANCE.md)


def test_every_module_named_by_its_file_name_exists():
    """`pacing.py`, `learner_files.py`: a file name without its folder names a file of the repository."""
    files = {p.name for d in TOP for p in (ROOT / d).rglob("*") if p.is_file()}
    bad = [f"{doc}: {name}" for doc, text in _doc_texts().items()
           for name in set(re.findall(r"(?<![\w/.-])([a-z_0-9]+\.(?:py|sh|toml|json5))(?![\w/])", text))
           if name not in files | OTHER_PROJECTS_FILES]
    assert not bad, "\n".join(bad)


def _test_names(path: Path) -> set[str]:
    tree = ast.parse(path.read_text())
    return {n.name for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.ClassDef))}


def test_every_cited_test_exists():
    bad = []
    for doc, cited, name in _cited(_doc_texts()):
        if name and (not (ROOT / cited).is_file() or name not in _test_names(ROOT / cited)):
            bad.append(f"{doc}: {cited}::{name}")
    assert not bad, "\n".join(bad)


def _resolves(dotted: str) -> bool:
    parts = dotted.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ImportError:
            continue
        for attr in parts[i:]:
            if not hasattr(obj, attr):
                return False
            obj = getattr(obj, attr)
        return True
    return False


def test_every_cited_module_and_name_exists():
    """`mam_core.reference.run_reference`, `services.roles.role.weights_screen`: importable."""
    bad = []
    for doc, text in _doc_texts().items():
        for dotted in set(DOTTED.findall(text)):
            if not _resolves(dotted.rstrip(".")):
                bad.append(f"{doc}: {dotted}")
    assert not bad, "\n".join(bad)


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, markup and punctuation dropped, spaces to `-`."""
    text = re.sub(r"[`*_]|\[([^\]]*)\]\([^)]*\)", lambda m: m.group(1) or "", heading.strip()).lower()
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


@cache
def headings(doc: str) -> tuple[str, ...]:
    return tuple(m.group(1).strip() for m in re.finditer(r"^#{1,6} (.+)$", _prose(_text(ROOT / doc)), re.M))


def anchors(doc: str) -> set[str]:
    seen: dict[str, int] = {}
    out = set()
    for h in headings(doc):
        s = slug(h)
        out.add(s if s not in seen else f"{s}-{seen[s]}")
        seen[s] = seen.get(s, 0) + 1
    return out


LINK = re.compile(r"\]\(([^)\s]*?)(?:#([\w-]+))?\)")
DOC_NAMES = "README|GUIDE|DESIGN-DECISIONS|RESULTS|RELIABILITY|PERFORMANCE|DEPLOY|APPLECOLLECT|ZENOH-NOTES"
# `docs/RESULTS.md, "Reference returns"`, `DESIGN-DECISIONS "Lock-step across processes"`, `README's "Layout"`
NAMED = re.compile(r"((?:docs/)?(?:" + DOC_NAMES + r")(?:\.md)?)(?:'s)?[`,]*\s*,?\s+\"([^\"]+)\"")


def test_every_link_and_its_anchor_exists():
    bad = []
    for path in DOCS:
        doc = path.relative_to(ROOT).as_posix()
        for target, anchor in LINK.findall(_prose(_text(path))):
            if target.startswith(("http://", "https://", "mailto:")):
                continue
            file = (path.parent / target).resolve() if target else path
            if not file.exists():
                bad.append(f"{doc}: link to {target}")
            elif anchor and file.suffix == ".md" and anchor not in anchors(file.relative_to(ROOT).as_posix()):
                bad.append(f"{doc}: {target or doc}#{anchor}: no such section")
    assert not bad, "\n".join(bad)


def test_every_section_cited_by_name_is_a_heading():
    """`docs/RESULTS.md, "Reference returns"` in a doc or in code names a heading of that file."""
    bad = []
    code = {p.relative_to(ROOT).as_posix(): re.sub(r"\n\s*#", " ", _text(p)) for p in CODE}  # comments joined
    sources = {**_doc_texts(), **code}
    for source, text in sources.items():
        for file, section in NAMED.findall(re.sub(r"\s+", " ", text)):
            file = file if file.endswith(".md") else f"{file}.md"
            doc = file if file.startswith("docs/") or file == "README.md" else f"docs/{file}"
            if not (ROOT / doc).is_file():
                bad.append(f"{source}: {file} does not exist")
            elif not any(section.lower() in h.lower() for h in headings(doc)):
                bad.append(f'{source}: {doc}, "{section}" is no heading there')
    assert not bad, "\n".join(bad)


def test_no_doc_cites_a_file_outside_the_repository():
    bad = [f"{doc}: {m}" for doc, text in _doc_texts().items()
           for m in re.findall(r"/work/\S+|DESIGN\.md|design contract", text)]
    assert not bad, "\n".join(bad)


# -- run options -----------------------------------------------------------------------------------
def test_every_run_option_is_in_help_or_in_the_table_of_file_only_keys():
    from services.run import options

    run_flags = flags_of(commands()["mam run"])
    readme = _text(ROOT / "README.md")
    table = re.search(r"^#{2,3} .*file only.*?\n(.*?)(?=^#{2,3} )", readme, re.S | re.M | re.I)
    assert table, "README has no section of the run options a TOML file alone takes"
    documented = set(re.findall(r"^\| `(\w+)` \|", table.group(1), re.M))
    for option in options.RUN_OPTIONS:
        if option.cli:
            assert set(option.decls[0].split("/")) <= run_flags, option.name
        else:
            assert option.name in documented, f"{option.name}: not in README's table of file-only keys"
    assert documented <= {o.name for o in options.RUN_OPTIONS if not o.cli}, "the table lists a key that is no option"


def test_every_run_config_field_is_a_run_option():
    """What a run's config.json holds is settable and so documented: the run options, less the
    resolved algorithm (its own fields are options) and the endpoint `mam run` picks."""
    import dataclasses

    from services.run import options
    from services.run.config import RunConfig

    names = {alias for o in options.RUN_OPTIONS for alias in (o.name, *o.aliases)}
    assert {f.name for f in dataclasses.fields(RunConfig)} - {"algo", "endpoint"} <= names


def test_mam_run_help_names_the_file_only_keys():
    from services.run import options

    epilog = commands()["mam run"].epilog or ""
    for option in options.RUN_OPTIONS:
        if not option.cli:
            assert option.name in epilog, option.name


# -- removed options -------------------------------------------------------------------------------
REMOVED = ("--collection", "--sync-every", "--band", "rate limiter", "rate-limited", "rate limit")


@pytest.mark.parametrize("doc", [p.relative_to(ROOT).as_posix() for p in DOCS])
def test_no_doc_mentions_a_removed_option(doc: str):
    text = _text(ROOT / doc).lower()
    assert not [r for r in REMOVED if r in text]


def test_the_removed_keys_are_the_ones_the_code_retires():
    from services.run.config import RETIRED_KEYS

    assert {k for k in RETIRED_KEYS} == {r[2:].replace("-", "_") for r in REMOVED if r.startswith("--")}


# -- the README as a newcomer reads it -------------------------------------------------------------
def test_the_readme_s_first_screen_leads_to_running_across_machines():
    readme = _text(ROOT / "README.md")
    assert "(#across-machines)" in "\n".join(readme.splitlines()[:8])
    assert "across-machines" in anchors("README.md")


def test_the_readme_indexes_every_doc_and_the_licence():
    readme = _text(ROOT / "README.md")
    for doc in (ROOT / "docs").glob("*.md"):
        assert f"](docs/{doc.name})" in readme, doc.name
    assert "](LICENSE)" in readme and "MIT" in (ROOT / "LICENSE").read_text()


def test_results_says_which_deviation_its_spread_is():
    from mam_lab.tables import SPREAD_TEXT

    head = "\n".join(_text(ROOT / "docs" / "RESULTS.md").splitlines()[:30])
    assert "divisor n" in head and "divisor n" in SPREAD_TEXT
