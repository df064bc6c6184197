"""The monitor as a person uses it: a real headless Chromium (Debian's ``chromium``, driven
through its DevTools protocol) opens the page of ``jetbot-rt run --backend real`` on the
PCA9685 emulator with a videotestsrc camera, sees the image and the bars change, clicks STOP;
the board is off and the run ends with exit 0, and the page says so."""

from __future__ import annotations

import time

import pytest
from cdp import Browser, chromium_path
from monitor_helpers import MonitoredRun

pytestmark = pytest.mark.skipif(chromium_path() is None,
                                reason="chromium is not installed (apt-get install chromium)")

IMAGE_SUM = """(() => {
  const img = document.getElementById("raw");
  if (!img.naturalWidth) return null;
  const c = document.createElement("canvas");
  c.width = img.naturalWidth; c.height = img.naturalHeight;
  const ctx = c.getContext("2d");
  ctx.drawImage(img, 0, 0);
  const d = ctx.getImageData(0, 0, c.width, c.height).data;
  let s = 0;
  for (let i = 0; i < d.length; i += 7) s = (s * 31 + d[i]) % 1000000007;
  return s;
})()"""


def distinct(browser: Browser, expression: str, count: int = 3, timeout: float = 20.0) -> set:
    """Samples of ``expression`` until ``count`` different values were seen."""
    seen: set = set()
    deadline = time.monotonic() + timeout
    while len(seen) < count and time.monotonic() < deadline:
        value = browser.evaluate(expression)
        if value is not None:
            seen.add(value)
        time.sleep(0.15)
    return seen


def test_a_browser_sees_the_robot_live_and_its_stop_button_ends_the_run(tmp_path) -> None:
    robot = MonitoredRun(tmp_path)
    browser = None
    try:
        url = robot.url()
        browser = Browser()
        browser.call("Page.enable")
        browser.call("Page.navigate", url=url)
        browser.wait_for('document.getElementById("state").textContent === "driving"')
        assert len(distinct(browser, IMAGE_SUM)) >= 3, "the live image does not change"
        assert len(distinct(browser, 'document.getElementById("mu-left-v").textContent')) >= 3
        assert not robot.chip.refresh().all_off()
        browser.screenshot(tmp_path / "driving.png")
        browser.click("#stop")
        banner = browser.wait_for('(() => { const e = document.getElementById("ended"); '
                                  'return !e.hidden && e.textContent; })()')
        assert "stop from the monitor page" in banner and "exit 0" in banner
        code, err = robot.finish()
        assert code == 0, err
        assert robot.chip.refresh().all_off()
    finally:
        if browser is not None:
            browser.close()
        robot.kill()
