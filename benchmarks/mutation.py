"""Mutation score of the safety-critical modules: how many plausible bugs the tests catch.

    python benchmarks/mutation.py                      # the sampled run (about 20 min, 2 jobs)
    python benchmarks/mutation.py --per-module 0       # every mutant (hours)

Mutants are cosmic-ray's (https://github.com/sixty-north/cosmic-ray): its operators (operator
and comparison swaps, constant changes, negated conditions, break/continue, exception and
boolean swaps...) plus one of ours that cosmic-ray lacks, ``RemoveStatement``: an assignment,
a call or a ``raise`` inside a function replaced by ``pass`` (a forgotten ``kick()``, a lost
``+= 1``). cosmic-ray writes each mutant to disk and runs a test command; the suite's tests
run the installed ``jetbot-rt`` in subprocesses, so the mutant must be what those import too.
Each of the ``--jobs`` workers therefore has its own copy of the repository and a venv whose
``jetbot_rt`` and console scripts are that copy's (the dependencies are this interpreter's).

No mutant is made inside a type annotation: these modules never evaluate them (``from
__future__ import annotations``), so ``str | None`` -> ``str - None`` is no bug.

Per mutant, only the tests of its module run (``MODULES``: fast ones first, with ``-x``; the
slow end-to-end ones only for a mutant the fast ones let through), with a timeout that counts
as killed (cosmic-ray's rule: a hang is caught). Not part of CI. Mutants are sampled
(``--per-module``, seeded) so that a run fits in ~25 minutes on a loaded 2-core machine; the
score is killed / (sampled - equivalent). Equivalent mutants (no behaviour can tell them from
the original) are listed in ``EQUIVALENT`` with the reason, matched by module and changed line.

Writes benchmarks/results/mutation.json and mutation.md.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import contextlib
import difflib
import importlib.metadata
import json
import os
import random
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path

from versions import stamp

try:
    import cosmic_ray
    import cosmic_ray.plugins
    from cosmic_ray.ast import ast_nodes, get_ast_from_path
    from cosmic_ray.mutating import mutate_code, use_mutation
    from cosmic_ray.operators.operator import Example, Operator
    from cosmic_ray.testing import run_tests
    from cosmic_ray.work_item import TestOutcome
    from parso.python.tree import Keyword
except ImportError:
    sys.exit("benchmarks/mutation.py needs cosmic-ray: pip install -e '.[mutation]'")

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"

FAST_SAFETY = ["tests/test_safety_contracts.py", "tests/test_safety.py",
               "tests/test_loop_schedule.py", "tests/test_loop.py"]
E2E_REAL = "tests/test_real_backend_e2e.py"
OWNERSHIP_STOP = [f"tests/test_fault_ownership.py::{name}" for name in (
    "test_stop_defeats_a_runtime_it_cannot_talk_to",
    "test_stop_never_reports_success_while_a_runtime_drives",
    "test_stop_names_a_process_it_cannot_defeat")]
MODULES: dict[str, tuple[list[str], list[str]]] = {
    # module: (fast tests, run first with -x; slow tests, run only if the fast ones pass)
    "jetbot_rt/runtime/safety.py": (FAST_SAFETY, ["tests/test_stop_event_order.py", E2E_REAL]),
    "jetbot_rt/runtime/loop.py": (["tests/test_loop_schedule.py", "tests/test_loop.py"],
                          ["tests/test_stop_event_order.py", E2E_REAL]),
    "jetbot_rt/runtime/actions.py": (["tests/test_actions.py", "tests/test_loop_schedule.py"],
                                     [E2E_REAL]),
    "jetbot_rt/runtime/policy.py": (["tests/test_policy.py", "tests/test_policy_orientation.py"],
                            ["tests/test_fault_input.py", E2E_REAL]),
    "jetbot_rt/hal/motors.py": (["tests/test_motors.py", "tests/test_i2c.py"],
                                ["tests/test_stop.py", E2E_REAL, *OWNERSHIP_STOP]),
    "jetbot_rt/hal/i2c.py": (["tests/test_i2c.py", "tests/test_motors.py"], ["tests/test_stop.py"]),
    "jetbot_rt/commands/stop.py": (["tests/test_stop.py"],
                                   ["tests/test_fault_config_read.py", *OWNERSHIP_STOP,
                                    E2E_REAL]),
    "jetbot_rt/service/runtime_dir.py": (["tests/test_stop.py", "tests/test_board_record.py"],
                                 ["tests/test_hostile_user.py", *OWNERSHIP_STOP]),
    "jetbot_rt/service/console.py": (
        ["tests/test_console_stream.py", "tests/test_fault_stalled_output.py"],
        ["tests/test_console_lines.py", E2E_REAL]),
    # the other end-to-end systemd tests run with the default 0.1 s in-process watchdog, which
    # a loaded machine trips now and then: a false kill here
    "jetbot_rt/service/systemd_notify.py": (
        ["tests/test_notify.py"],
        ["tests/test_systemd_e2e.py::TestWatchdogPingsComeFromCompletedTicks"]),
}


@dataclass(frozen=True)
class Equivalent:
    """Mutants of ``original`` (a changed line, stripped) in ``module`` that no test can tell
    from the original, with the reason. ``mutated``: the exact mutated lines, or empty for
    every mutant of that line whose operator name contains ``operator``."""

    module: str
    original: str
    mutated: tuple[str, ...]
    reason: str
    operator: str = ""
    unless: str = ""
    """With ``operator``: not when the mutated line contains this."""

    def matches(self, mutant: Mutant) -> bool:
        def bare(text: str) -> str:  # cosmic-ray writes "read= 2", "( 1.02)"
            return text.replace(" ", "")

        if mutant.module != self.module or bare(mutant.original) != bare(self.original):
            return False
        if self.mutated:
            return bare(mutant.mutated) in {bare(m) for m in self.mutated}
        return (bool(self.operator) and self.operator in mutant.operator
                and not (self.unless and self.unless in mutant.mutated))


_CLAMP = "return low if value < low else high if value > high else value"
_PID = "pid = (_positive_int(pid_text) or -1) if pid_text else None"
_DIM = "return value if isinstance(value, int) and value > 0 else None"
_FULL = ("the full-on or full-off bit is set: the PCA9685 ignores the counts then (datasheet "
         "7.3.3), so another count below 0x100 changes no output")
_RESHAPE = "mu = np.asarray(output, dtype=np.float64).reshape(-1)"
_PRESCALE_SLEEP = ("bus.writeto(address, bytes((MODE1, MODE1_SLEEP | MODE1_AI)))  # PRE_SCALE "
                   "needs SLEEP")
EQUIVALENT = [
    Equivalent("jetbot_rt/hal/motors.py", _PRESCALE_SLEEP,
               tuple(_PRESCALE_SLEEP.replace("|", op) for op in ("^", "+", "%")),
               "the byte keeps SLEEP (0x10), all PRE_SCALE needs; auto-increment matters to "
               "none of the single-register writes that follow"),
    Equivalent("jetbot_rt/hal/motors.py",
               "mode1 = self.bus.transfer(self.address, [payload, bytes((MODE1,))], read=1)",
               ("mode1 = self.bus.transfer(self.address, [payload, bytes((MODE1,))], read=2)",),
               "reading MODE2 after MODE1 changes nothing: only mode1[0] is used"),
    Equivalent("jetbot_rt/hal/motors.py", "if TYPE_CHECKING:", ("if not TYPE_CHECKING:",),
               "the type-only import also works at run time (no import cycle)"),
    Equivalent("jetbot_rt/runtime/policy.py", _RESHAPE,
               tuple(_RESHAPE.replace("(-1)", f"({v})") for v in ("~1", "- 2", "-2")),
               "numpy takes any negative size as 'all the rest' (checked on numpy 2.4)"),
    Equivalent("jetbot_rt/hal/motors.py", "SLEEP = bytes((MODE1, MODE1_SLEEP | MODE1_AI))",
               ("SLEEP = bytes((MODE1, MODE1_SLEEP ^ MODE1_AI))",
                "SLEEP = bytes((MODE1, MODE1_SLEEP + MODE1_AI))",
                "SLEEP = bytes((MODE1, MODE1_SLEEP % MODE1_AI))"),
               "0x10 and 0x20 share no bit: |, ^ and + give the same byte; % gives SLEEP "
               "alone: asleep, auto-increment changes no output, and a drive set-up sets it"),
    Equivalent("jetbot_rt/hal/motors.py", "return bytes((0, FULL_BIT, 0, 0))", (), _FULL,
               operator="NumberReplacer", unless="-"),
    Equivalent("jetbot_rt/hal/motors.py", "return bytes((0, 0, 0, FULL_BIT))", (), _FULL,
               operator="NumberReplacer", unless="-"),
    Equivalent("jetbot_rt/runtime/actions.py", _CLAMP,
               (_CLAMP.replace("value < low", "value <= low"),
                _CLAMP.replace("value > high", "value >= high")),
               "at value == bound both return the bound"),
    Equivalent("jetbot_rt/hal/motors.py", "OSCILLATOR_HZ = 25_000_000",
               ("OSCILLATOR_HZ = 25000001", "OSCILLATOR_HZ = 24999999"),
               "1 Hz on 25 MHz changes no prescale value: checked for every 0.1 Hz from 1 Hz "
               "to 5 kHz"),
    Equivalent("jetbot_rt/commands/stop.py", "motors = MotorsConfig()", ("pass",),
               "_motors() already returns the default MotorsConfig with the error it reports"),
    Equivalent("jetbot_rt/commands/stop.py",
               "except Exception as exc:  # the stop must go out whatever the config holds",
               (), "unreachable defence in depth: load_config turns every failure it can meet "
               "(bytes, size, nesting, TOML, FIFO, values) into UsageError "
               "(tests/test_fault_config_read.py)", operator="ExceptionReplacer"),
    Equivalent("jetbot_rt/runtime/loop.py", '"t": round(self.t_start - t0, 6),',
               ('"t": round(self.t_start - t0, 7),', '"t": round(self.t_start - t0, 5),'),
               "the record's t rounded to 0.1 or 10 us instead of 1 us; ticks are ms apart"),
    Equivalent("jetbot_rt/service/systemd_notify.py", _PID,
               tuple(_PID.replace("or -1", f"or {v}") for v in ("not 1", "- 0", "- 2", "~1", "+1")),
               "an unparsable WATCHDOG_PID must name no process: -1, 0, -2 and False all do "
               "(only a positive pid can equal ours); +1 differs only for a runtime that is "
               "PID 1 itself (a container's init), which no test here can be"),
    Equivalent("jetbot_rt/commands/stop.py", "time.sleep(0.02)", (), "the poll period "
               "of the wait for the bus's owner to end: owned() is read again after the loop, "
               "so a longer poll changes only how soon (by under a second) stop notices, never "
               "what it reports or its exit; only a timing assertion could see it (a negative "
               "sleep raises: not equivalent)", operator="NumberReplacer", unless="-"),
    Equivalent("jetbot_rt/service/runtime_dir.py",
               "_DIR_FLAGS = os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC",
               ("_DIR_FLAGS = os.O_RDONLY ^ os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC",
                "_DIR_FLAGS = os.O_RDONLY + os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC"),
               "O_RDONLY is 0 (POSIX leaves it to the system; Linux, the only target, defines "
               "it 0): 0 ^ x and 0 + x are 0 | x"),
    Equivalent("jetbot_rt/service/console.py",
               "stream.drained(mark, max(0.0, deadline - time.monotonic()))",
               ("stream.drained(mark, max(-1.0, deadline - time.monotonic()))",),
               "Event.wait with a timeout <= 0 does not block either way (threading.Condition"
               ".wait: a non-blocking acquire), and a wait that timed out is what it reports"),
    Equivalent("jetbot_rt/service/console.py",
               "stream.drained(mark, max(0.0, deadline - time.monotonic()))",
               ("stream.drained(mark, max(1.0, deadline - time.monotonic()))",),
               "timing only: the exit's drain of a stalled stream waits at least 1 s instead "
               "of what is left of DRAIN_S; what is written, lost and said is the same, and "
               "the tests assert no durations"),
    Equivalent("jetbot_rt/service/console.py", "except (OSError, ValueError, AttributeError):",
               (), "fileno() is called only on the interpreter's own sys.__stdout__/__stderr__ "
               "or a TextIOWrapper console made itself, which all have it: AttributeError "
               "cannot be raised there (defence in depth)", operator="ExceptionReplacer"),
    Equivalent("jetbot_rt/runtime/loop.py", "break", ("continue",),
               "every break in ControlLoop.run follows a latch.trip (or a latch.wait that "
               "returned True), so the latch is tripped: with continue, the while loop's own "
               "test (while not self.latch.tripped) ends it at once, nothing run between"),
    Equivalent("jetbot_rt/runtime/policy.py", _DIM, (_DIM.replace("value > 0", "value != 0"),),
               "onnxruntime reports an unknown or negative dimension as None or a name, never "
               "a negative int (checked: dim_value -1 reads back as None)"),
]


def equivalent_reason(mutant: Mutant) -> str:
    for rule in EQUIVALENT:
        if rule.matches(mutant):
            return rule.reason
    # ``*`` (keyword-only marker) -> ``/`` in a signature: cosmic-ray's Mul_Div also swaps the
    # star of ``def f(self, a, *, start=0)``; every caller passes those by keyword either way
    if mutant.operator.endswith("ReplaceBinaryOperator_Mul_Div") and (
            (mutant.original, mutant.mutated) == ("*,", "/,")
            or (mutant.mutated == mutant.original.replace("*, ", "/, ", 1)
                and "*, " in mutant.original and ": " in mutant.original)):
        return ("the keyword-only marker * made a positional-only marker /: the parameters "
                "after it are still passed by keyword, as every caller does")
    return ""


@dataclass(frozen=True)
class Planted:
    """A bug planted by hand (issue 9's list): ``old`` replaced by ``new`` in ``module``."""

    name: str
    module: str
    old: str
    new: str
    tests: tuple[str, ...]


PLANTED = [
    Planted("latch flag set after its callbacks", "jetbot_rt/runtime/safety.py",
            "            self._tripped.set()\n        for callback in self._callbacks:\n"
            "            callback(reason)\n",
            "        for callback in self._callbacks:\n            callback(reason)\n"
            "        self._tripped.set()\n",
            ("tests/test_safety_contracts.py",)),
    Planted("overrun count's + 1 lost", "jetbot_rt/runtime/loop.py",
            "// self.period) + 1", "// self.period)", ("tests/test_loop_schedule.py",)),
    Planted("NCHW frames fed with height and width swapped", "jetbot_rt/runtime/policy.py",
            "tensor.transpose(2, 0, 1)", "tensor.transpose(2, 1, 0)",
            ("tests/test_policy_orientation.py",)),
    Planted("the main thread pings WATCHDOG=1", "jetbot_rt/commands/run_phases.py",
            "            loop_thread.join(0.05)\n",
            "            loop_thread.join(0.05)\n"
            "            self.services.notifier.tick(time.monotonic(), rt.status)\n",
            ("tests/test_systemd_e2e.py::TestWatchdogPingsComeFromCompletedTicks",)),
    Planted("export parity check skipped", "jetbot_rt/train/export.py",
            "    error = parity_error(model, data)", "    error = 0.0",
            ("tests/test_export_parity.py",)),
    Planted("stop waits without limit for a hung write", "jetbot_rt/runtime/safety.py",
            "self._lock.acquire(timeout=STOP_LOCK_TIMEOUT_S)", "self._lock.acquire()",
            ("tests/test_safety_contracts.py",)),
    Planted("safe_stop logged before the motors are zero", "jetbot_rt/commands/run_phases.py",
            "        drive = self.drive = GuardedDrive(robot.drive, rt.latch)\n"
            "        rt.shutdown.zero_last(drive)\n"
            "        # registered after the drive's own zeroing callback: the event is logged once"
            " it is done\n        rt.latch.on_trip(rt.log_trip)\n",
            "        rt.latch.on_trip(rt.log_trip)\n"
            "        drive = self.drive = GuardedDrive(robot.drive, rt.latch)\n"
            "        rt.shutdown.zero_last(drive)\n",
            ("tests/test_stop_event_order.py",)),
    Planted("GStreamer child not killed with its parent", "jetbot_rt/hal/gst_camera.py",
            "    _PRCTL(PR_SET_PDEATHSIG, signal.SIGKILL)\n", "",
            ("tests/test_gst_camera.py::TestAQuietChildDiesWithItsParent",)),
    Planted("watchdog trips a timeout late", "jetbot_rt/runtime/safety.py",
            "remaining = self._last_kick + self.timeout - self.clock()",
            "remaining = self._last_kick + 2 * self.timeout - self.clock()",
            ("tests/test_safety_contracts.py",)),
    Planted("stop exits 0 when the stop cannot be written", "jetbot_rt/commands/stop.py",
            "        return EXIT_BOARD_UNREACHABLE\n", "        return exit_code\n",
            ("tests/test_stop.py",)),
]


@contextlib.contextmanager
def planted_bug(path: Path, planted: Planted) -> Iterator[bool]:
    """The bug written into ``path`` for the block; yields False when ``old`` is not found
    exactly once (the code changed: the list needs updating)."""
    original = path.read_text()
    if original.count(planted.old) != 1:
        yield False
        return
    path.write_text(original.replace(planted.old, planted.new))
    try:
        yield True
    finally:
        path.write_text(original)


class RemoveStatement(Operator):
    """An assignment, a bare call or a ``raise`` in a function body becomes ``pass``."""

    def mutation_positions(self, node):  # type: ignore[no-untyped-def]
        if _removable(node):
            yield (node.start_pos, node.end_pos)

    def mutate(self, node, index):  # type: ignore[no-untyped-def]
        return Keyword("pass", node.start_pos, prefix=node.get_first_leaf().prefix)

    @classmethod
    def examples(cls):  # type: ignore[no-untyped-def]
        return (Example("def f():\n    g()\n", "def f():\n    pass\n"),)


def _removable(node) -> bool:  # type: ignore[no-untyped-def]
    if node.parent is None or node.parent.type != "simple_stmt":
        return False
    if node.type == "atom_expr":  # a call as a statement: its last trailer is "(...)"
        last = node.children[-1]
        if last.type != "trailer" or last.children[0].value != "(":
            return False
    elif node.type not in ("expr_stmt", "raise_stmt"):
        return False
    scope = node.parent
    while scope is not None and scope.type not in ("funcdef", "classdef", "file_input"):
        scope = scope.parent
    return scope is not None and scope.type == "funcdef"


OUR_OPERATORS = {"jetbot/RemoveStatement": RemoveStatement}
LEFT_OUT: list[str] = []
"""Test files that failed without any mutant in this run's baseline (named in the results)."""


def _in_annotation(node) -> bool:  # type: ignore[no-untyped-def]
    """Inside a type annotation: never evaluated in these modules (``from __future__ import
    annotations``), so a mutant there (``str | None`` -> ``str - None``) is not a bug."""
    child, parent = node, node.parent
    while parent is not None:
        siblings = parent.children
        if parent.type == "tfpdef" and child is siblings[2]:
            return True
        if parent.type == "annassign" and child is siblings[1]:
            return True
        if parent.type == "funcdef":
            index = siblings.index(child)
            return index > 0 and getattr(siblings[index - 1], "value", None) == "->"
        child, parent = parent, parent.parent
    return False


def operator_instance(name: str) -> Operator:
    if name in OUR_OPERATORS:
        return OUR_OPERATORS[name]()
    return cosmic_ray.plugins.get_operator(name)()


def operator_names() -> list[str]:
    names = [n for n in cosmic_ray.plugins.operator_names()
             if not cosmic_ray.plugins.get_operator(n).arguments()]
    return sorted(names) + sorted(OUR_OPERATORS)


@dataclass
class Mutant:
    module: str
    operator: str
    occurrence: int
    line: int
    original: str = ""
    mutated: str = ""
    outcome: str = "pending"  # killed, survived, timeout (killed), equivalent, skipped, error
    stage: str = ""  # which tests killed it: fast, slow
    seconds: float = 0.0
    equivalent_reason: str = ""
    output_tail: str = field(default="", repr=False)


def enumerate_mutants(module: str) -> list[Mutant]:
    path = ROOT / module
    tree = get_ast_from_path(path)
    mutants = []
    for name in operator_names():
        operator = operator_instance(name)
        occurrence = 0
        for node in ast_nodes(tree):
            for start, _end in operator.mutation_positions(node):
                if not _in_annotation(node):
                    mutants.append(Mutant(module, name, occurrence, start[0]))
                occurrence += 1
    return mutants


def describe(mutant: Mutant, source: str) -> bool:
    """Fill in the changed line; False when the operator produces no change there."""
    mutated = mutate_code(source, operator_instance(mutant.operator), mutant.occurrence)
    if mutated is None:
        return False
    before, after = source.splitlines(), mutated.splitlines()
    removed, added = [], []
    for line in difflib.unified_diff(before, after, lineterm="", n=0):
        if line.startswith("-") and not line.startswith("---"):
            removed.append(line[1:].strip())
        elif line.startswith("+") and not line.startswith("+++"):
            added.append(line[1:].strip())
    if not removed and not added:
        return False
    mutant.original, mutant.mutated = " / ".join(removed), " / ".join(added)
    return True


# ---- workers: a copy of the repository each, with a venv that imports that copy ---------------


def make_worker(base: Path, index: int) -> Path:
    # tests/test_hostile_user.py runs the copy's interpreter and code as a second uid, which
    # imports modules lazily: mkdtemp's 0700 would hide them (ModuleNotFoundError)
    base.chmod(0o755)
    copy = base / f"worker-{index}"
    files = subprocess.run(["git", "ls-files", "-co", "--exclude-standard", "-z"], cwd=ROOT,
                           capture_output=True, check=True).stdout.decode().split("\0")
    for name in filter(None, files):
        source = ROOT / name
        if source.is_file():
            target = copy / name
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, target)
    venv = copy / ".venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    [site] = list((venv / "lib").glob("python3*/site-packages"))
    deps = [p for p in sys.path if p.endswith("site-packages") and Path(p).is_dir()]
    (site / "jetbot_rt_mutation.pth").write_text("\n".join([str(copy), *deps]) + "\n")
    for script, module in (("jetbot-rt", "jetbot_rt.cli"), ("jetbot-train", "jetbot_rt.train.cli")):
        path = venv / "bin" / script
        path.write_text(f"#!{venv / 'bin' / 'python'}\nimport sys\nfrom {module} import main\n"
                        "sys.exit(main())\n")
        path.chmod(0o755)
    for cache in copy.rglob("__pycache__"):
        shutil.rmtree(cache, ignore_errors=True)
    return copy


def test_command(copy: Path, tests: list[str]) -> str:
    venv_bin = copy / ".venv" / "bin"
    path = f"{venv_bin}:{os.environ.get('PATH', '/usr/bin:/bin')}"
    return (f"env -C {copy} PATH={path} {venv_bin / 'python'} -m pytest -x -q "
            f"-p no:cacheprovider {' '.join(tests)}")


def baseline(copy: Path, test: str) -> float | None:
    """Seconds the unmutated ``test`` takes; None when it fails (twice: a loaded machine
    can make a sound test fail once)."""
    for _attempt in range(2):
        t0 = time.monotonic()
        outcome, output = run_tests(test_command(copy, [test]), 900)
        if outcome == TestOutcome.SURVIVED:
            return time.monotonic() - t0
    tail = "\n".join(str(output).splitlines()[-5:])
    print(f"WARNING: {test} fails without any mutant; left out of this run:\n{tail}",
          file=sys.stderr, flush=True)
    return None


def run_mutant(copy: Path, mutant: Mutant, timeouts: dict[str, float]) -> None:
    t0 = time.monotonic()
    if mutant.operator == "planted":
        planted = next(p for p in PLANTED if p.name == mutant.original)
        stages: tuple[list[str], ...] = ([t for t in planted.tests if t not in LEFT_OUT], [])
        mutation = planted_bug(copy / planted.module, planted)
    else:
        stages = MODULES[mutant.module]
        mutation = use_mutation(copy / mutant.module, operator_instance(mutant.operator),
                                mutant.occurrence)
    with mutation as applied:
        if applied is False or (isinstance(applied, tuple) and applied[1] is None):
            mutant.outcome = "error"  # a planted bug whose code changed: update PLANTED
            return
        for stage, tests in zip(("fast", "slow"), stages, strict=True):
            if not tests:
                continue
            outcome, output = run_tests(test_command(copy, tests), timeouts[stage])
            if outcome == TestOutcome.KILLED:
                mutant.outcome = "timeout" if output == "timeout" else "killed"
                mutant.stage = stage
                break
        else:
            mutant.outcome = "survived"
            mutant.output_tail = (output or "")[-400:] if isinstance(output, str) else ""
    mutant.seconds = round(time.monotonic() - t0, 1)


# ---- the run ----------------------------------------------------------------------------------


def uptime() -> str:
    """The 1, 5 and 15 minute load averages."""
    try:
        return " ".join(Path("/proc/loadavg").read_text().split()[:3])
    except OSError:
        return "?"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--per-module", type=int, default=30,
                        help="mutants sampled per module (0: all)")
    parser.add_argument("--seed", type=int, default=9)
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--budget-s", type=float, default=25 * 60,
                        help="stop starting new mutants after this many seconds")
    parser.add_argument("--modules", nargs="*", default=list(MODULES))
    parser.add_argument("--no-planted", action="store_true",
                        help="leave out issue 9's planted bugs (PLANTED)")
    parser.add_argument("--out", default=str(RESULTS / "mutation.json"))
    parser.add_argument("--reclassify", action="store_true",
                        help="re-apply EQUIVALENT to the results in --out and rewrite them; "
                             "runs nothing")
    parser.add_argument("--retest", action="store_true",
                        help="with --reclassify: run the survivors again against the tests "
                             "as they are now")
    args = parser.parse_args()
    if args.reclassify:
        reclassify(Path(args.out), args.retest, args.jobs)
        return 0

    t_start = time.monotonic()
    load_before = uptime()
    rng = random.Random(args.seed)
    population: dict[str, int] = {}
    chosen: list[Mutant] = []
    for module in args.modules:
        source = (ROOT / module).read_text()
        mutants = enumerate_mutants(module)
        population[module] = len(mutants)
        rng.shuffle(mutants)
        picked = 0
        for mutant in mutants:
            if args.per_module and picked >= args.per_module:
                break
            if not describe(mutant, source):
                continue
            picked += 1
            reason = equivalent_reason(mutant)
            if reason:
                mutant.outcome, mutant.equivalent_reason = "equivalent", reason
            chosen.append(mutant)
    rng.shuffle(chosen)
    print(f"{len(chosen)} mutants sampled of {sum(population.values())}", flush=True)
    planted = [] if args.no_planted else [
        Mutant(p.module, "planted", -1, 0, original=p.name, mutated=p.new.strip()[:120])
        for p in PLANTED]
    chosen += planted  # the workers take from the end: the planted bugs first

    left_out = LEFT_OUT
    base = Path(tempfile.mkdtemp(prefix="jetbot-rt-mutation-"))
    try:
        copies = [make_worker(base, i) for i in range(args.jobs)]
        # the unmutated tests must pass in the copies (those that do not are left out and
        # named in the results); their times set the timeouts
        files = sorted({t for m in args.modules for stage in MODULES[m] for t in stage}
                       | {t for m in planted for p in PLANTED if p.name == m.original
                          for t in p.tests})
        with concurrent.futures.ThreadPoolExecutor(args.jobs) as pool:
            jobs = {t: pool.submit(baseline, copies[i % len(copies)], t)
                    for i, t in enumerate(files)}
            durations = {t: job.result() for t, job in jobs.items()}
        left_out.extend(t for t, d in durations.items() if d is None)
        for module in args.modules:
            MODULES[module] = tuple(  # type: ignore[assignment]
                [t for t in stage if durations[t] is not None] for stage in MODULES[module])
        stage_s = {stage: max(sum(durations[t] or 0.0 for t in MODULES[m][i])
                              for m in args.modules) for i, stage in enumerate(("fast", "slow"))}
        timeouts = {"fast": max(60.0, 3 * stage_s["fast"]), "slow": max(180.0, 3 * stage_s["slow"])}
        print(f"baseline {sum(d or 0.0 for d in durations.values()):.0f} s, timeouts {timeouts}",
              flush=True)

        pending = [m for m in chosen if m.outcome == "pending"]
        lock = threading.Lock()
        done = [0]

        def worker(copy: Path) -> None:
            while True:
                with lock:
                    if not pending:
                        return
                    if time.monotonic() - t_start > args.budget_s:
                        for mutant in pending:
                            mutant.outcome = "skipped"
                        pending.clear()
                        return
                    mutant = pending.pop()
                run_mutant(copy, mutant, timeouts)
                with lock:
                    done[0] += 1
                    print(f"[{done[0]}/{len(chosen)}] {mutant.outcome:9} {mutant.module}:"
                          f"{mutant.line} {mutant.operator} ({mutant.seconds} s)", flush=True)

        threads = [threading.Thread(target=worker, args=(c,)) for c in copies]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
    finally:
        shutil.rmtree(base, ignore_errors=True)

    report(chosen, population, args, time.monotonic() - t_start, load_before, left_out)
    return 0


def reclassify(path: Path, retest: bool = False, jobs: int = 2) -> None:
    """Equivalent-mutant decisions made after a run, applied to its recorded results; with
    ``retest``, the survivors run again against the tests as they are now (tests added for
    survivors after the run; the product code must be the same)."""
    old = json.loads(path.read_text())
    mutants = [Mutant(**m) for m in old["mutants"]]
    for mutant in mutants:
        if mutant.outcome in ("survived", "equivalent"):
            reason = equivalent_reason(mutant)
            mutant.outcome = "equivalent" if reason else "survived"
            mutant.equivalent_reason = reason
    if retest:
        LEFT_OUT.extend(old.get("tests_left_out", []))
        for module in MODULES:
            MODULES[module] = tuple(  # type: ignore[assignment]
                [t for t in stage if t not in LEFT_OUT] for stage in MODULES[module])
        survivors = [m for m in mutants if m.outcome == "survived"]
        base = Path(tempfile.mkdtemp(prefix="jetbot-rt-mutation-"))
        try:
            copies = [make_worker(base, i) for i in range(jobs)]
            timeouts = {"fast": 120.0, "slow": 400.0}
            with concurrent.futures.ThreadPoolExecutor(jobs) as pool:
                list(pool.map(lambda i: [run_mutant(copies[i], m, timeouts)
                                         for m in survivors[i::jobs]], range(jobs)))
        finally:
            shutil.rmtree(base, ignore_errors=True)
        for mutant in survivors:
            if mutant.outcome != "survived":
                mutant.stage += " (retest)"
        print(f"retested {len(survivors)} survivors: "
              f"{sum(m.outcome != 'survived' for m in survivors)} killed now", flush=True)
    args = argparse.Namespace(seed=old["seed"], per_module=old["per_module"], jobs=old["jobs"],
                              out=str(path))
    population = {m: v["population"] for m, v in old["modules"].items()}
    report(mutants, population, args, old["wall_s"], old["load_before"],
           old.get("tests_left_out", []), load_after=old["load_after"])


def report(mutants: list[Mutant], population: dict[str, int], args: argparse.Namespace,
           wall_s: float, load_before: str, left_out: list[str],
           load_after: str | None = None) -> None:
    per_module = {}
    for module in population:
        mine = [m for m in mutants if m.module == module and m.operator != "planted"]
        counts = {k: sum(m.outcome == k for m in mine)
                  for k in ("killed", "timeout", "survived", "equivalent", "skipped", "error")}
        tested = counts["killed"] + counts["timeout"] + counts["survived"]
        per_module[module] = {"population": population[module], "sampled": len(mine), **counts,
                              "score": round((counts["killed"] + counts["timeout"]) / tested, 3)
                              if tested else None}
    killed = sum(v["killed"] + v["timeout"] for v in per_module.values())
    tested = killed + sum(v["survived"] for v in per_module.values())
    result = {
        "tool": f"cosmic-ray {importlib.metadata.version('cosmic-ray')} operators"
                " + RemoveStatement",
        "seed": args.seed, "per_module": args.per_module, "jobs": args.jobs,
        "wall_s": round(wall_s), "load_before": load_before,
        "load_after": load_after or uptime(),
        "score": round(killed / tested, 3) if tested else None,
        "tests_left_out": left_out,
        "tests": {m: {"fast": MODULES[m][0], "slow": MODULES[m][1]} for m in population},
        "killed": killed, "tested": tested,
        "modules": per_module,
        "planted": [{"bug": m.original, "module": m.module, "outcome": m.outcome,
                     "seconds": m.seconds} for m in mutants if m.operator == "planted"],
        "survivors": [asdict(m) for m in mutants
                      if m.outcome == "survived" and m.operator != "planted"],
        "equivalent": [asdict(m) for m in mutants if m.outcome == "equivalent"],
        "mutants": [{k: v for k, v in asdict(m).items() if k != "output_tail"} for m in mutants],
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(stamp(result), indent=1) + "\n")
    lines = [
        "# Mutation score (benchmarks/mutation.py)", "",
        f"{result['tool']}; {sum(v['sampled'] for v in per_module.values())} mutants sampled "
        f"(seed {args.seed}, up to {args.per_module or 'all'} per module) of "
        f"{sum(population.values())}; {args.jobs} jobs, {wall_s / 60:.1f} min, load "
        f"{load_before} -> {result['load_after']}.", "",
        f"**Score: {killed}/{tested} = {100 * killed / max(tested, 1):.1f} % killed** "
        "(equivalent mutants set aside).", "",
        *([f"Tests left out (they failed without any mutant): {', '.join(left_out)}.", ""]
          if left_out else []),
        "| module | mutants | sampled | killed | survived | equivalent | skipped | score |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for module, v in per_module.items():
        score = "-" if v["score"] is None else f"{100 * v['score']:.0f} %"
        lines.append(f"| {module} | {v['population']} | {v['sampled']} | "
                     f"{v['killed'] + v['timeout']} | {v['survived']} | {v['equivalent']} | "
                     f"{v['skipped']} | {score} |")
    lines += ["", "## Issue 9's planted bugs (always run, not in the score)", ""]
    for m in result["planted"]:
        lines.append(f"- {m['bug']} ({m['module']}): {m['outcome']}")
    lines += ["", "## Survivors", ""]
    for m in result["survivors"]:
        lines.append(f"- {m['module']}:{m['line']} {m['operator']}: `{m['original']}` -> "
                     f"`{m['mutated']}`")
    lines += ["", "## Equivalent (set aside)", ""]
    for m in result["equivalent"]:
        lines.append(f"- {m['module']}:{m['line']} `{m['original']}` -> `{m['mutated']}`: "
                     f"{m['equivalent_reason']}")
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines[:8]))


if __name__ == "__main__":
    sys.exit(main())
