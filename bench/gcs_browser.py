"""Is the ground station still usable in a browser with 100 vehicles flying?

    python -m bench.gcs_browser [--quick] [--vehicles 100]     # writes gcs_browser.json

A real `covey fleet-sim` flies N vehicles (all taking off, then a broadcast goto) on a mesh that
a real `GroundStation` hosts; real Debian Chromium (headless, software WebGL, as in the browser
tests) opens the station through Playwright. Measured in the page, while the fleet flies:

- frames per second (requestAnimationFrame callbacks per second: the 3D view redrawing);
- main-thread lag: a 50 ms timer's lateness, p50/p99/max (what a click waits for at worst);
- input round trip: typing into the "Targets" field until the page shows the new value.

Skipped (with a reason) when chromium or Playwright is missing. Playwright is a test
dependency: `make test` installs it, or `.venv/bin/pip install -e '.[test]'` (the runtime venv
of `make demo` has none).
"""

from __future__ import annotations

import argparse
import shutil
import time

import numpy as np

from bench import common
from comms.session import embedded_router, free_tcp_port

FLEET = "benchgcs"
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]

LAG_PROBE_JS = """(ms) => new Promise(resolve => {
  const lags = []; let frames = 0; let last = performance.now();
  const tick = () => { frames++; if (!done) requestAnimationFrame(tick); };
  let done = false; requestAnimationFrame(tick);
  const timer = setInterval(() => { const now = performance.now(); lags.push(now - last - 50); last = now; }, 50);
  setTimeout(() => { done = true; clearInterval(timer); resolve({frames, lags}); }, ms);
})"""


def measure_page(page, window_s: float) -> dict:
    t0 = time.perf_counter()
    res = page.evaluate(LAG_PROBE_JS, int(window_s * 1000))
    wall_s = time.perf_counter() - t0
    lags = np.maximum(np.array(res["lags"], dtype=float), 0.0)
    return {
        "window_s": round(wall_s, 2),
        "frames_per_s": round(res["frames"] / window_s, 1),
        "timer_lag_ms_p50": common.pct(lags, 50),
        "timer_lag_ms_p99": common.pct(lags, 99),
        "timer_lag_ms_max": round(float(lags.max()), 1) if len(lags) else 0.0,
        "timer_samples": int(len(lags)),
    }


def input_round_trip_ms(page, repeats: int) -> list[float]:
    box = page.locator(  # the input of the viser control labelled "Targets"
        "xpath=//label[normalize-space()='Targets']/ancestor::div[contains(@class,'mantine-Flex-root')][1]//input"
    )
    out = []
    for k in range(repeats):
        text = f"{k % 9 + 1}"
        t0 = time.perf_counter()
        box.fill(text)
        box.evaluate("(el, v) => el.value === v || Promise.reject(new Error(el.value))", text)
        out.append((time.perf_counter() - t0) * 1e3)
    return out


def main(quick: bool = False, vehicles: int = 100, viewport: tuple[int, int] = (1200, 800)) -> dict:
    from comms.commands import new_nonce
    from comms.schema import Command
    from groundstation.station import GcsConfig, GroundStation

    chromium = shutil.which("chromium")
    try:
        from playwright import sync_api
    except ImportError:
        sync_api = None
    if chromium is None or sync_api is None:
        common.say("skipped: needs Debian chromium and playwright (make test installs both)")
        return {"skipped": "chromium or playwright missing"}
    window_s = 3.0 if quick else 15.0
    settle_s = 0.5 if quick else 1.0  # scale of the waits for the page and the fleet
    port = free_tcp_port()
    cfg = GcsConfig(
        mesh=embedded_router(port, fleet=FLEET),
        port=0,
        geofence_radius_m=400.0,
        view_radius_m=60.0,
        key_file=None,
    )
    result: dict = {
        "vehicles": vehicles,
        "quick": quick,
        "chromium": "headless, software WebGL",
        "viewport": f"{viewport[0]}x{viewport[1]}",
    }
    with GroundStation(cfg) as gs, common.children() as kids:
        sim = kids.start(
            "-m",
            "covey_cli",
            "fleet-sim",
            "--vehicles",
            str(vehicles),
            "--fleet",
            FLEET,
            "--connect",
            f"tcp/127.0.0.1:{port}",
            "--spacing-m",
            "8",
            "--cruise-speed-m-s",
            "2",
            "--geofence-radius-m",
            "0",
        )
        sim.wait_for("READY", timeout_s=120)
        ids = set(range(1, vehicles + 1))
        if not gs.presence.wait_for(lambda v, _g: v >= ids, timeout_s=60):
            raise RuntimeError("fleet-sim vehicles did not all appear")
        with sync_api.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=chromium, headless=True, args=CHROMIUM_ARGS)
            page = browser.new_page(viewport={"width": viewport[0], "height": viewport[1]})
            page.set_default_timeout(120_000)
            page.goto(gs.url)
            page.get_by_role("button", name="Takeoff").wait_for()
            page.locator("canvas").first.wait_for()
            time.sleep(3.0 * settle_s)  # shader compiles and the first scene
            result["landed"] = measure_page(page, window_s)
            common.say(
                f"landed: {result['landed']['frames_per_s']} frames/s, "
                f"timer lag p99 {result['landed']['timer_lag_ms_p99']:.0f} ms"
            )
            up = gs.mesh.send_command(
                Command.takeoff(8.0, nonce=new_nonce(), stamp_ns=0), expect=ids, timeout_s=10
            )
            if not up.ok:
                raise RuntimeError(f"takeoff: {up.summary()}")
            time.sleep(6.0 * settle_s)
            go = gs.mesh.send_command(
                Command.goto_local(150.0, 40.0, -8.0, nonce=new_nonce(), stamp_ns=0),
                expect=ids,
                timeout_s=10,
            )
            if not go.ok:
                raise RuntimeError(f"goto: {go.summary()}")
            time.sleep(2.0 * settle_s)
            result["flying"] = measure_page(page, window_s)
            f = result["flying"]
            common.say(
                f"{vehicles} flying: {f['frames_per_s']} frames/s, timer lag p50 {f['timer_lag_ms_p50']:.0f} ms "
                f"p99 {f['timer_lag_ms_p99']:.0f} ms max {f['timer_lag_ms_max']:.0f} ms"
            )
            rt = input_round_trip_ms(page, 3 if quick else 20)
            result["input_round_trip_ms_p50"] = common.pct(rt, 50)
            result["input_round_trip_ms_max"] = round(float(max(rt)), 1)
            common.say(
                f"typing into a field: p50 {result['input_round_trip_ms_p50']:.0f} ms, "
                f"max {result['input_round_trip_ms_max']:.0f} ms"
            )
            browser.close()
        upd = np.array(gs.update_times_s[-200:]) * 1e3
        result["server_update_ms_p50"] = common.pct(upd, 50)
        result["server_update_ms_p99"] = common.pct(upd, 99)
    common.write_json("gcs_browser", result)
    return result


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--vehicles", type=int, default=100)
    ap.add_argument("--viewport", default="1200x800", help="browser window WIDTHxHEIGHT")
    a = ap.parse_args()
    w, h = (int(x) for x in a.viewport.split("x"))
    main(a.quick, a.vehicles, (w, h))
