"""The docs site's MkDocs hook (mkdocs.yml ``hooks:``): the pages that must not drift from the
code are made from it at build time, and links into the rest of the repository keep working.

- ``reference/config.md``: every ``[section] key`` of ``jetbot_rt.config.sections.Config``
  with its type, default and accepted values from the schema, its description from the key's
  docstring (else its comment in ``jetbot_rt/data/default-config.toml``), then that file.
- ``reference/jetbot-rt.md``, ``reference/jetbot-train.md``: every subcommand and flag, from
  the argparse parsers the commands themselves use.
- ``index.md``: README.md, its links rewritten for the site (README is the one front page).
- Files outside ``docs/`` that a page links to (``../benchmarks/results/train.md``, a marker
  in ``jetbot_rt/data/``) are copied into the site at their repository path, and the links are
  rewritten to them: a results page reads on the site as it does on GitHub. A link to a file
  that does not exist is left alone, so ``mkdocs build --strict`` fails on it.

``python scripts/docs_site.py OUT`` writes the three reference pages to OUT without MkDocs.
"""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import os
import posixpath
import re
import sys
import typing
from collections.abc import Iterator
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
DOCS = "docs"
DEFAULT_CONFIG = ROOT / "jetbot_rt" / "data" / "default-config.toml"
GENERATED_NOTE = ("Generated at build time by `scripts/docs_site.py` from {source}; edit "
                  "that, not this page.")
COPIED_FROM_REPO = ("benchmarks/", "jetbot_rt/", "examples/", "systemd/", "scripts/", "tests/",
                    "constraints/")
"""Where a docs page may link outside docs/ and have the file copied into the site."""


# ---- configuration reference ------------------------------------------------------------


def _attribute_docs(cls: type) -> dict[str, str]:
    """The docstring under each field of a config section (the trainer's reader of them);
    ``[randomize]``'s class is made at run time, so its written base speaks for it."""
    from jetbot_rt.train.flags import field_docs

    try:
        return field_docs(cls)
    except (OSError, TypeError):  # no source: RandomizeConfig (sim/config.py)
        return field_docs(cls.__mro__[1])


KEY_LINE = re.compile(r"^#?\s*([a-z_][a-z0-9_]*)\s*=\s*(.*)$")


def default_config_comments(text: str) -> dict[tuple[str, str], str]:
    """``(section, key)`` -> the comment that documents it in the default config: the comment
    block right above the key (or above a commented-out ``# key = ...`` line), else the
    comment at the end of its line."""
    out: dict[tuple[str, str], str] = {}
    section, block = "", []  # type: str, list[str]
    for raw in text.splitlines():
        line = raw.strip()
        if line.startswith("[") and line.endswith("]"):
            section, block = line.strip("[]"), []
            continue
        if not line:
            block = []
            continue
        bare = line.lstrip("#").strip() if line.startswith("#") else line
        match = KEY_LINE.match(bare)
        if match and ("=" in bare) and not bare.endswith(":"):
            key, rest = match.groups()
            inline = rest.split("#", 1)[1].strip() if "#" in rest else ""
            said = " ".join(block) or inline
            if said and (section, key) not in out:
                out[(section, key)] = said
            continue  # the block above a key documents the keys right below it too
        if line.startswith("#"):
            block.append(line.lstrip("#").strip())
    return out


def _cell(text: str) -> str:
    """Text for one cell of a Markdown table: one line, ``|`` escaped, rST quotes as code."""
    text = " ".join(text.replace("``", "`").split())
    return text.replace("|", "\\|")


def _toml_value(value: Any) -> str:
    if value is None:
        return "none"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return f'"{value}"'
    if isinstance(value, list):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    return repr(value)


def config_keys() -> Iterator[tuple[str, str, dataclasses.Field, str]]:
    """Every ``(section, key, field, type)`` the config accepts, in the schema's order."""
    from jetbot_rt.config.schema import key_types, type_name
    from jetbot_rt.config.sections import Config

    for section in dataclasses.fields(Config):
        cls = section.default_factory()  # type: ignore[misc]
        hints = key_types(type(cls))
        for f in dataclasses.fields(cls):
            hint = hints[f.name]
            optional = type(None) in typing.get_args(hint)
            yield section.name, f.name, f, type_name(hint) + (" or none" if optional else "")


def config_reference() -> str:
    from jetbot_rt.config.sections import Config
    from jetbot_rt.sim.config import randomized_knobs
    from jetbot_rt.train.flags import field_default

    comments = default_config_comments(DEFAULT_CONFIG.read_text(encoding="utf-8"))
    ranges = {spec.key or name: (name, spec) for name, spec in randomized_knobs()}
    lines = [
        "# Configuration keys",
        "",
        GENERATED_NOTE.format(source="the schema (`jetbot_rt/config/sections.py`, "
                              "`jetbot_rt/sim/config.py`, `jetbot_rt/monitor/config.py`) and "
                              "`jetbot_rt/data/default-config.toml`"),
        "",
        "A config is a TOML file (`--config FILE`); flags override it. An unknown section or "
        "key, a wrong type or a value out of range is one line naming `[section] key` and exit "
        "code 2. `jetbot-train` reads the same file: `[sim]`, `[randomize]`, `[actions]` and "
        "`[loop]` shape its env, and a `[train]` table (and `[train.model]`, below) sets the "
        "trainer's options ([jetbot-train](jetbot-train.md)); `jetbot-rt` skips `[train]`.",
        "",
    ]
    current = ""
    for section, key, f, type_text in config_keys():
        if section != current:
            current = section
            cls = type(getattr(Config(), section))
            doc = inspect.getdoc(cls) if cls.__doc__ else ""
            lines += ["", f"## [{section}]", ""]
            if doc and not doc.startswith(cls.__name__ + "("):
                lines += [doc.replace("``", "`"), ""]
            docs = _attribute_docs(cls)
        said = docs.get(key) or comments.get((section, key), "")
        if section == "randomize" and key in ranges and not said:
            knob, spec = ranges[key]
            said = f"Per-episode range of `[sim] {knob}` ({spec.draw}). {spec.doc}"
        accepted = f.metadata.get("expected", "")
        lines += [f"`{key} = {_toml_value(field_default(f))}`",
                  f":   *{_cell(type_text + (': ' + accepted if accepted else ''))}.* "
                  f"{_cell(said)}", ""]
    lines += train_keys()
    lines += ["", "## The default file", "",
              "`jetbot-rt install-service` writes this file (every key with its default) to "
              "`/etc/jetbot-rt/config.toml`:", "", "```toml",
              DEFAULT_CONFIG.read_text(encoding="utf-8").rstrip(), "```", ""]
    return "\n".join(lines)


def train_keys() -> list[str]:
    """``[train]`` and ``[train.model]``: the trainers' parameters (``PPOArgs``, ``DAggerArgs``,
    ``ModelConfig``), each with the flag that sets it too."""
    from jetbot_rt.train.cli import flag
    from jetbot_rt.train.flags import field_default, field_docs
    from jetbot_rt.train.hyperparams import DAggerArgs, ModelConfig, PPOArgs

    lines = ["", "## [train] and [train.model] (jetbot-train only)", "",
             "The trainer's parameters: the dataclass default, then the task's default "
             "(`Task.training`), then this table, then the flag. A PPO-only key with "
             "`--algo dagger` (or the reverse) is an error.", ""]
    ppo, dagger = {f.name: f for f in dataclasses.fields(PPOArgs)}, \
        {f.name: f for f in dataclasses.fields(DAggerArgs)}
    docs = {**field_docs(DAggerArgs), **field_docs(PPOArgs)}
    for name in [*ppo, *(n for n in dagger if n not in ppo)]:
        if name == "model":
            continue
        f = ppo.get(name) or dagger[name]
        algo = "PPO and DAgger" if name in ppo and name in dagger else \
            ("PPO" if name in ppo else "DAgger")
        lines += [f"`{name} = {_toml_value(field_default(f))}`",
                  f":   *{algo}; `{flag(name)}`.* {_cell(docs.get(name, ''))}", ""]
    lines += ["### [train.model]", ""]
    model_docs = field_docs(ModelConfig)
    for f in dataclasses.fields(ModelConfig):
        lines += [f"`{f.name} = {_toml_value(field_default(f))}`",
                  f":   *`{flag('model.' + f.name)}`.* {_cell(model_docs.get(f.name, ''))}", ""]
    return lines


# ---- command-line reference --------------------------------------------------------------


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def jetbot_rt_parser() -> argparse.ArgumentParser:
    """``jetbot-rt``'s parser with every subcommand's arguments added (the command itself adds
    only the chosen one's)."""
    import importlib

    from jetbot_rt.cli import build_parser

    parser, modules = build_parser()
    for name, sub in _subparsers(parser).items():
        importlib.import_module(modules[name]).add_arguments(sub)
    return parser


def jetbot_train_parser() -> argparse.ArgumentParser:
    """``jetbot-train``'s parser; it imports the trainer's torch-free modules (gymnasium, from
    the ``docs`` extra). A missing module is one line, not a traceback."""
    try:
        from jetbot_rt.train.cli import build_parser

        return build_parser()
    except ModuleNotFoundError as exc:
        raise SystemExit(f"docs: building jetbot-train's parser imported {exc.name!r}, which "
                         "is not installed (the docs extra brings what the parser needs: "
                         "gymnasium; the parser must not import more)") from None


def _help_of(parser: argparse.ArgumentParser, action: argparse.Action) -> str:
    formatter = parser._get_formatter()
    return formatter._expand_help(action) if action.help else ""


def _flags_of(action: argparse.Action) -> str:
    """``--out OUT``, ``--algo {ppo,dagger}``, ``--resume, --no-resume``: as ``--help``
    writes an argument, in code (braces outside code are attribute lists to Markdown)."""
    if not action.option_strings:
        return f"`{action.metavar or action.dest}`"
    value = ""
    if action.nargs != 0:
        if action.choices:
            value = " {" + ",".join(str(c) for c in action.choices) + "}"
        else:
            value = " " + (action.metavar or action.dest.upper())
    return ", ".join(f"`{s}{value}`" for s in action.option_strings)


def _arguments(parser: argparse.ArgumentParser) -> list[str]:
    """Each argument of ``parser`` as a definition: the flags, then the help."""
    out: list[str] = []
    for action in parser._actions:
        if isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)):
            continue
        if action.help == argparse.SUPPRESS:
            continue
        required = " (required)" if action.required and action.option_strings else ""
        said = _help_of(parser, action) or (
            "" if action.default in (None, False) else f"(default: {action.default})")
        out += [_flags_of(action), f":   {_cell(said) or '(no help text)'}{required}", ""]
    return out


def cli_reference(prog: str) -> str:
    """Every subcommand of ``prog`` (``jetbot-rt`` or ``jetbot-train``) and every argument."""
    parser = jetbot_rt_parser() if prog == "jetbot-rt" else jetbot_train_parser()
    source = "`jetbot_rt/cli.py` and `jetbot_rt/commands/*.py`" if prog == "jetbot-rt" else \
        "`jetbot_rt/train/cli.py` and `jetbot_rt/train/flags.py`"
    lines = [f"# {prog}", "", GENERATED_NOTE.format(source=f"the argparse parsers ({source})"),
             "", parser.description or "", ""]
    if parser.epilog:
        lines += [parser.epilog, ""]
    lines += ["Every command: bad input is one line on stderr and exit code 2. "
              f"`{prog} COMMAND --help` prints the same as below.", ""]
    for name, sub in _subparsers(parser).items():
        usage = sub.format_usage().strip().removeprefix("usage: ")
        lines += [f"## {prog} {name}", "", (sub.description or "").replace("``", "`"), "",
                  "```", usage, "```", "", *_arguments(sub)]
    return "\n".join(lines)


def reference_pages() -> dict[str, str]:
    """``reference/...md`` -> its Markdown; the parsers format usage at a fixed width (argparse
    reads ``COLUMNS``), whatever the terminal that builds them."""
    saved = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = "80"
    try:
        return {
            "reference/config.md": config_reference(),
            "reference/jetbot-rt.md": cli_reference("jetbot-rt"),
            "reference/jetbot-train.md": cli_reference("jetbot-train"),
        }
    finally:
        if saved is None:
            del os.environ["COLUMNS"]
        else:
            os.environ["COLUMNS"] = saved


# ---- links out of docs/ ------------------------------------------------------------------

LINK = re.compile(r"(!?\[[^\]]*\]\()([^)\s#]+)(#[^)\s]*)?(\s+\"[^\"]*\")?\)")


def _outside_text(markdown: str) -> Iterator[tuple[bool, str]]:
    """``(is_prose, chunk)`` over ``markdown``, fenced code blocks apart (never rewritten)."""
    parts = re.split(r"(^```.*?^```[^\n]*$)", markdown, flags=re.MULTILINE | re.DOTALL)
    for i, part in enumerate(parts):
        yield i % 2 == 0, part


def _repo_target(page_repo_path: str, target: str) -> str | None:
    """The repository path a relative link of the page at ``page_repo_path`` points to."""
    if re.match(r"^[a-z][a-z0-9+.-]*:", target) or target.startswith("/"):
        return None  # http:, mailto:, absolute
    joined = posixpath.normpath(posixpath.join(posixpath.dirname(page_repo_path), target))
    return None if joined.startswith("..") else joined


def _site_path(repo_path: str) -> str:
    """Where a repository file lives in the site: docs/X at X, anything else at its path."""
    prefix = DOCS + "/"
    return repo_path[len(prefix):] if repo_path.startswith(prefix) else repo_path


def copied(repo_path: str) -> bool:
    return repo_path.startswith(COPIED_FROM_REPO) and (ROOT / repo_path).is_file()


def rewrite_links(markdown: str, page_repo_path: str) -> tuple[str, set[str]]:
    """The page's links as the site needs them, and the repository files outside docs/ they
    reach (to be copied). A link to a missing file is left as written: the strict build
    reports it."""
    page_site = _site_path(page_repo_path)
    wanted: set[str] = set()

    def one(match: re.Match[str]) -> str:
        head, target, anchor, title = match.groups()
        repo_path = _repo_target(page_repo_path, target)
        if repo_path is None:
            return match.group(0)
        if not repo_path.startswith(DOCS + "/"):
            if not copied(repo_path):
                return match.group(0)
            wanted.add(repo_path)
        new = posixpath.relpath(_site_path(repo_path), posixpath.dirname(page_site) or ".")
        return f"{head}{new}{anchor or ''}{title or ''})"

    out = "".join(LINK.sub(one, chunk) if prose else chunk
                  for prose, chunk in _outside_text(markdown))
    return out, wanted


# ---- MkDocs events ------------------------------------------------------------------------

_REPO_PATH_OF: dict[str, str] = {}
"""A page's site path -> the repository file it was made from (for its relative links)."""


def on_files(files: Any, config: Any) -> Any:
    from mkdocs.structure.files import File

    pages = reference_pages()
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    pages["index.md"] = readme
    _REPO_PATH_OF.clear()
    _REPO_PATH_OF["index.md"] = "README.md"
    for uri, text in pages.items():
        if files.get_file_from_path(uri) is not None:
            raise SystemExit(f"docs/{uri} exists, but the docs build makes it: remove it")
        files.append(File.generated(config, uri, content=text))
        _REPO_PATH_OF.setdefault(uri, f"{DOCS}/{uri}")
    # Copy what any page (or a copied results page) links to outside docs/.
    todo = [(f"{DOCS}/{f.src_uri}", Path(f.abs_src_path).read_text(encoding="utf-8"))
            for f in files if f.is_documentation_page() and f.abs_src_path]
    todo.append(("README.md", readme))
    done: set[str] = set()
    while todo:
        repo_path, text = todo.pop()
        _, wanted = rewrite_links(text, repo_path)
        for path in sorted(wanted - done):
            done.add(path)
            files.append(File(path, str(ROOT), config["site_dir"], config["use_directory_urls"]))
            _REPO_PATH_OF[path] = path
            if path.endswith(".md"):
                todo.append((path, (ROOT / path).read_text(encoding="utf-8")))
    return files


def on_page_markdown(markdown: str, page: Any, config: Any, files: Any) -> str:
    uri = page.file.src_uri
    repo_path = _REPO_PATH_OF.get(uri, f"{DOCS}/{uri}")
    return rewrite_links(markdown, repo_path)[0]


if __name__ == "__main__":
    out = Path(sys.argv[1] if len(sys.argv) > 1 else "build/reference")
    for name, text in reference_pages().items():
        path = out / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text, encoding="utf-8")
        print(path)
