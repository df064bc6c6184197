"""A ``jetbot-rt run --monitor`` in a subprocess (the PCA9685 emulator, a videotestsrc camera
or the sim) and the URL its monitor printed; shared by the monitor's tests."""

from __future__ import annotations

import os
import queue
import re
import subprocess
import sys
import threading
import time
from pathlib import Path

from jetbot_rt.testing.pca9685_emulator import PCA9685Emulator


class MonitoredRun:
    def __init__(self, root: Path, backend: str = "real", monitor: str = "0",
                 source: str = "gst:videotestsrc is-live=true pattern=ball",
                 extra: tuple[str, ...] = (), command: str = "run",
                 config_extra: str = "") -> None:
        self.root = root
        self.config = root / "robot.toml"
        # patient thresholds: on a loaded machine a camera's 0.15 s stall would end the run
        # (exit 3) before the browser has opened the page
        self.config.write_text(f'[camera]\nsource = "{source}"\nstart_timeout = 5\n'
                               "[motors]\ni2c_retries = 1\n"
                               "[loop]\nmax_frame_age = 1.0\nwatchdog_timeout = 1.0\n"
                               + config_extra)
        self.chip_file = root / "chip.json"
        self.chip = PCA9685Emulator(0x60, state_file=self.chip_file)
        env = dict(os.environ, JETBOT_RT_RUNTIME_DIR=str(root / "run"))
        board = ["--board-emulator", str(self.chip_file)] if backend == "real" else []
        self.process = subprocess.Popen(
            [sys.executable, "-m", "jetbot_rt.cli", command, "--backend", backend,
             "--config", str(self.config), "--monitor", monitor, "--duration", "60",
             *board, *extra],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
        self.lines: queue.Queue[str] = queue.Queue()
        self.out: list[str] = []
        threading.Thread(target=self._pump, daemon=True).start()

    def _pump(self) -> None:
        assert self.process.stdout is not None
        for line in self.process.stdout:
            self.out.append(line)
            self.lines.put(line)

    def url(self, timeout: float = 60.0) -> str:
        """The monitor's URL, once the run says it listens."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                line = self.lines.get(timeout=0.2)
            except queue.Empty:
                if self.process.poll() is not None:
                    raise AssertionError(f"run ended ({self.process.returncode}): "
                                         f"{self.process.stderr.read()}") from None
                continue
            match = re.match(r"monitor: (http://\S+/) ", line)
            if match:
                return match.group(1)
        raise AssertionError("the monitor's URL was not printed")

    def finish(self, timeout: float = 30.0) -> tuple[int, str]:
        self.process.wait(timeout)
        assert self.process.stderr is not None
        return self.process.returncode, self.process.stderr.read()

    def kill(self) -> None:
        if self.process.poll() is None:
            self.process.kill()
            self.process.wait()
