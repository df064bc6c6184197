"""The trainers' hyperparameters as ``jetbot-train train`` flags: one flag per field of
``PPOArgs``, ``DAggerArgs`` and ``ModelConfig``, its help the field's docstring, its default
the dataclass's (and the task's, where it differs).

Precedence: ``PPOArgs`` defaults < ``TASK_DEFAULTS[task]`` < the ``[train]`` table of
``--config`` < flags given on the command line.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import inspect
import itertools
import textwrap
from typing import Any

from jetbot_rt.errors import UsageError
from jetbot_rt.train.hyperparams import (
    SIGNED,
    TASK_DEFAULTS,
    CurriculumOptions,
    DAggerArgs,
    ModelConfig,
    PPOArgs,
)

SKIPPED = ("task", "config", "model")
"""Fields with flags of their own: ``--task``, ``--config``; ``model`` as ``--model-*``."""
FLAG_NAMES = {"total_timesteps": "--timesteps"}
"""Fields whose flag is not their name: one name in --help and the docs (the field's own,
``--total-timesteps``, is still accepted, unlisted)."""
OPTIONAL_VALUE = {"ray": {"nargs": "?", "const": "local", "metavar": "ADDRESS"}}
"""Flags whose value may be left out (``--ray`` alone: Ray on this machine)."""


def positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {value}")
    return value


def field_docs(cls: type) -> dict[str, str]:
    """Attribute docstrings (the string literal after each field) of a dataclass and of the
    dataclasses it derives from."""
    docs: dict[str, str] = {}
    for base in reversed(cls.__mro__[1:]):
        if dataclasses.is_dataclass(base):
            docs.update(field_docs(base))
    tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    body = tree.body[0].body  # type: ignore[attr-defined]
    for node, following in itertools.pairwise(body):
        if (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)
                and isinstance(following, ast.Expr)
                and isinstance(following.value, ast.Constant)
                and isinstance(following.value.value, str)):
            docs[node.target.id] = " ".join(following.value.value.split())
    return docs


def field_default(spec: dataclasses.Field) -> Any:
    """A dataclass field's default (its factory's value), None where it has none."""
    if spec.default is not dataclasses.MISSING:
        return spec.default
    if spec.default_factory is not dataclasses.MISSING:
        return spec.default_factory()
    return None


def _help(doc: str, default: Any, per_task: dict[str, Any]) -> str:
    text = doc.replace("``", "").replace("%", "%%")
    shown = [f"default {default!r}" if not isinstance(default, str) else f"default {default}"]
    shown += [f"{task}: {value}" for task, value in per_task.items()]
    return f"{text} ({'; '.join(shown)})"


def _add(group: argparse._ArgumentGroup, flags: list[str], dest: str, spec: dataclasses.Field,
         doc: str, per_task: dict[str, Any]) -> None:
    default = field_default(spec)
    kwargs: dict[str, Any] = {"dest": dest, "default": argparse.SUPPRESS,
                              "help": _help(doc, default, per_task)}
    annotation = str(spec.type)
    if dest in OPTIONAL_VALUE:
        kwargs.update(OPTIONAL_VALUE[dest])
    elif annotation == "bool":
        kwargs["action"] = argparse.BooleanOptionalAction
    elif annotation.startswith("tuple[int"):
        kwargs.update(type=positive_int, nargs=len(default), metavar="N")
    else:
        base = annotation.replace(" | None", "")
        integer = int if dest in SIGNED else positive_int
        kwargs["type"] = {"int": integer, "float": float}.get(base, str)
        kwargs["metavar"] = dest.split(".")[-1].upper()
    group.add_argument(*flags, **kwargs)


def add_ppo_arguments(parser: argparse.ArgumentParser) -> None:
    """One ``--field-name`` per ``PPOArgs`` field, per ``DAggerArgs`` field that PPO has not,
    and ``--model-name`` per ``ModelConfig``."""
    group = parser.add_argument_group("PPO options (also settable in a [train] table)")
    docs = field_docs(PPOArgs)
    curriculum = parser.add_argument_group(
        "curriculum (PPO and DAgger; docs/CURRICULUM.md)")
    shared = {f.name for f in dataclasses.fields(CurriculumOptions)}
    for spec in dataclasses.fields(PPOArgs):
        if spec.name in SKIPPED:
            continue
        if spec.name in shared:
            _add(curriculum, ["--" + spec.name.replace("_", "-")], spec.name, spec,
                 docs.get(spec.name, ""), {})
            continue
        per_task = {t: d[spec.name] for t, d in TASK_DEFAULTS.items() if spec.name in d}
        own = "--" + spec.name.replace("_", "-")
        _add(group, [FLAG_NAMES.get(spec.name, own)], spec.name, spec, docs.get(spec.name, ""),
             per_task)
        if spec.name in FLAG_NAMES:
            group.add_argument(own, dest=spec.name, type=positive_int,
                               default=argparse.SUPPRESS, help=argparse.SUPPRESS)
    dagger_group = parser.add_argument_group(
        "DAgger options (--algo dagger; it shares --out, --seed, --resume, --init, --num-envs, "
        "--workers, --learning-rate, --device, --torch-threads, --progress with PPO, each with "
        "DAgger's own default)")
    dagger_docs, ppo_names = field_docs(DAggerArgs), {f.name for f in dataclasses.fields(PPOArgs)}
    for spec in dataclasses.fields(DAggerArgs):
        if spec.name not in ppo_names and spec.name not in SKIPPED:
            _add(dagger_group, ["--" + spec.name.replace("_", "-")], spec.name, spec,
                 dagger_docs.get(spec.name, ""), {})
    model_group = parser.add_argument_group("network options (a [train.model] table)")
    model_docs = field_docs(ModelConfig)
    for spec in dataclasses.fields(ModelConfig):
        per_task = {t: d["model"][spec.name] for t, d in TASK_DEFAULTS.items()
                    if spec.name in d.get("model", {})}
        _add(model_group, ["--model-" + spec.name.replace("_", "-")], "model." + spec.name,
             spec, model_docs.get(spec.name, ""), per_task)


def overrides(namespace: argparse.Namespace, table: dict[str, Any] | None,
              algo: str = "ppo") -> dict[str, Any]:
    """The ``[train]`` table updated with the flags given on the command line; a flag of the
    other algorithm is an error."""
    known = {"ppo": PPOArgs, "dagger": DAggerArgs}
    names = {f.name for f in dataclasses.fields(known[algo])} - set(SKIPPED)
    every = set().union(*({f.name for f in dataclasses.fields(c)} for c in known.values()))
    result: dict[str, Any] = {k: v for k, v in (table or {}).items() if k != "model"}
    model_table = (table or {}).get("model", {})
    if not isinstance(model_table, dict):
        raise UsageError("[train] model must be a table ([train.model])")
    model: dict[str, Any] = dict(model_table)
    for key, value in vars(namespace).items():
        if key.startswith("model."):
            model[key[len("model."):]] = value
        elif key in names:
            result[key] = value
        elif key in every - set(SKIPPED):
            flag = "--" + key.replace("_", "-")
            raise UsageError(f"{flag} is not an option of --algo {algo}")
    if model:
        result["model"] = model
    return result
