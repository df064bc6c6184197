"""The docs site (mkdocs.yml, scripts/docs_site.py): the reference pages are made from the code,
so they name every config key and every flag; the site builds with warnings as errors, so a
broken link or a page left out of the nav fails here as it fails in CI."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import pytest
from script_module import load_script

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def site_hook():
    return load_script("scripts/docs_site.py")


@pytest.fixture(scope="module")
def pages(site_hook) -> dict[str, str]:
    return site_hook.reference_pages()


def _section_of(page: str, heading: str) -> str:
    """The part of ``page`` under the ``## heading`` line, up to the next one."""
    start = page.index(f"\n## {heading}\n")
    end = page.find("\n## ", start + 1)
    return page[start:end if end != -1 else None]


def test_the_config_reference_names_every_key_of_every_section_with_what_it_does(
        site_hook, pages):
    page = pages["reference/config.md"]
    keys = list(site_hook.config_keys())
    assert len(keys) > 80
    for section, key, _, _ in keys:
        part = _section_of(page, f"[{section}]")
        match = re.search(rf"^`{key} = [^`]*`\n:   \*(.+)$", part, re.MULTILINE)
        assert match, f"[{section}] {key} is missing from the reference"
        said = match.group(1).split(".* ", 1)[-1]
        assert len(said) > 10, f"[{section}] {key} has no description: {match.group(0)!r}"


def test_a_key_documented_only_in_the_default_file_takes_its_comment(site_hook):
    comments = site_hook.default_config_comments(
        "[motors]\n# I2C bus number and the chip's address.\ni2c_bus = 1\naddress = 0x60\n\n"
        "[randomize]\nlatency = [0.0, 0.1]  # s\n# enabled = true\n")
    assert comments[("motors", "i2c_bus")] == "I2C bus number and the chip's address."
    assert comments[("motors", "address")] == comments[("motors", "i2c_bus")]
    assert comments[("randomize", "latency")] == "s"
    assert ("randomize", "enabled") not in comments


@pytest.mark.parametrize("prog", ["jetbot-rt", "jetbot-train"])
def test_the_cli_reference_names_every_subcommand_and_flag(site_hook, pages, prog):
    parser = (site_hook.jetbot_rt_parser() if prog == "jetbot-rt"
              else site_hook.jetbot_train_parser())
    page = pages[f"reference/{prog}.md"]
    subcommands = site_hook._subparsers(parser)
    assert len(subcommands) >= 4
    for name, sub in subcommands.items():
        part = _section_of(page, f"{prog} {name}")
        terms = " ".join(re.findall(r"^(`.*)\n:   \S", part, re.MULTILINE))
        for action in sub._actions:
            if action.help == argparse.SUPPRESS:  # a hidden alias: --help does not show it
                continue
            for flag in action.option_strings:
                if flag not in ("-h", "--help"):
                    assert re.search(rf"`{re.escape(flag)}[ `]", terms), \
                        f"{prog} {name} {flag} is missing from the reference"


def test_links_out_of_docs_reach_the_copied_file_and_a_broken_one_is_left_for_the_build(
        site_hook):
    text = ("[raw](../benchmarks/results/train.md) [gone](../benchmarks/results/nope.md) "
            "[page](SIM.md#speed) [web](https://example.org/x)\n```\n[code](../x.md)\n```\n")
    out, wanted = site_hook.rewrite_links(text, "docs/BENCHMARKS.md")
    assert "[raw](benchmarks/results/train.md)" in out
    assert "[gone](../benchmarks/results/nope.md)" in out  # mkdocs --strict reports it
    assert "[page](SIM.md#speed)" in out and "(https://example.org/x)" in out
    assert "[code](../x.md)" in out
    assert wanted == {"benchmarks/results/train.md"}
    readme, _ = site_hook.rewrite_links("![robot](docs/images/weak_wheel.png)", "README.md")
    assert readme == "![robot](images/weak_wheel.png)"


def test_the_site_builds_with_warnings_as_errors(tmp_path, monkeypatch):
    """What .ci/run runs, in this process (the reference pages' imports are loaded already):
    mkdocs build --strict, where a broken link, a missing page or a page left out of the nav
    aborts the build."""
    from mkdocs.commands.build import build
    from mkdocs.config import load_config

    monkeypatch.setenv("NO_MKDOCS_2_WARNING", "1")
    site = tmp_path / "site"
    build(load_config(str(ROOT / "mkdocs.yml"), site_dir=str(site), strict=True))
    for page in ("index.html", "reference/config/index.html", "reference/jetbot-rt/index.html",
                 "reference/jetbot-train/index.html", "BENCHMARKS/index.html"):
        assert (site / page).is_file(), page
    assert "rate_hz" in (site / "reference/config/index.html").read_text(encoding="utf-8")
    assert (site / "benchmarks/results/forward_blind/index.html").is_file()  # copied in


def test_the_readme_is_a_front_page_whose_first_commands_install_and_run_then_test():
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    assert len(text.splitlines()) <= 200
    blocks = re.findall(r"^```sh\n(.*?)\n```", text, re.MULTILINE | re.DOTALL)
    assert blocks[0].startswith("python3 -m venv .venv && ") and "jetbot-rt run --backend sim" \
        in blocks[0]
    assert blocks[1].startswith("apt-get update && ") and blocks[1].endswith("pytest -q -n 2")


def test_the_config_reference_names_every_train_key_with_its_flag(pages):
    import dataclasses

    from jetbot_rt.train.hyperparams import DAggerArgs, ModelConfig, PPOArgs

    page = pages["reference/config.md"]
    train = _section_of(page, "[train] and [train.model] (jetbot-train only)")
    for cls in (PPOArgs, DAggerArgs, ModelConfig):
        for f in dataclasses.fields(cls):
            if f.name != "model":
                assert re.search(rf"^`{f.name} = .*`\n:   \*.*`--", train, re.MULTILINE), f.name
