"""@vbusd/core's previous-frame clock (web/core/src/previous.js; spec virtual-bones.md 21) against
values worked out by hand: the previous fade time and weight of each instance (a time-sampled fade
at t - dt, the others as they are), a reset instance's current values and flag for exactly one
frame, and one clear error for a frame interval that is not > 0. Run in the session's Chromium on
the page `vbusd view` serves (the core has no engine to import)."""

from __future__ import annotations

import pytest

from vbusd.web.browser import ViewerPage
from vbusd.web.server import ViewerServer

from tests.helpers.browser import PAGE, SAMPLE

SCRIPT = """async () => {
  const { PreviousFrame, previousClipTime, checkFrameInterval } = await import('./vbusd-core/index.js');
  // (fadeTimeOffset, fadePlaybackRate, fadeWeight) now; the weight is time-sampled 0 at 0.5 s, 1 at 1.5 s.
  const fade = [[1.5, 2.0, 0.9], [0.0, 1.0, 0.0], [-0.5, 0.5, 0.9]];
  const samples = { fadeWeight: { times: [0.5, 1.5], values: [0, 0, 0, 1, 1, 1] } };
  const clock = new PreviousFrame(3);
  clock.reset(1);
  const first = Array.from(clock.update(1.0, 0.25, (i) => fade[i], samples));
  const firstTime = clock.previousTime;
  const second = Array.from(clock.update(1.25, 0.25, (i) => fade[i], samples));
  let error = '';
  try { checkFrameInterval(0); } catch (e) { error = e.message; }
  return { first, firstTime, second, clip: previousClipTime(1.25, 0.5, 3.0, 0.5), error };
}"""


def test_previous_frame_clock_by_hand(browser):
    with ViewerServer(SAMPLE / "stadium_crowd_vb.usda") as server:
        page = ViewerPage(browser, server.url + PAGE)
        try:
            assert page.error == "", page.error
            got = page.page.evaluate(SCRIPT)
            assert page.errors() == [], page.errors()
        finally:
            page.close()
    # t = 1, dt = 0.25: previous time 0.75, the sampled weight there 0.25.
    # Instance 0: 1.5 + 2 * 0.75 = 3.0; instance 1 is reset: its current fade time 0 + 1 * 1.0 and
    # weight 0, flag 1; instance 2: -0.5 + 0.5 * 0.75 = -0.125.
    assert got["firstTime"] == 0.75
    assert got["first"] == pytest.approx([3.0, 0.25, 0, 0, 1.0, 0.0, 1, 0, -0.125, 0.25, 0, 0], abs=1e-6)
    # t = 1.25: previous time 1.0, weight 0.5; the reset held one frame.
    assert got["second"] == pytest.approx([3.5, 0.5, 0, 0, 1.0, 0.5, 0, 0, 0.0, 0.5, 0, 0], abs=1e-6)
    assert got["clip"] == pytest.approx(1.25 + 0.5 * 2.5)
    assert "frame interval dt must be a number > 0" in got["error"] and "\n" not in got["error"]
