"""Traffic on the station and in Foxglove: the scene layer against a real viser server, the whole
station in real Chromium fed by a real `covey intruder` mesh stream, and the Foxglove channels."""

from __future__ import annotations

import io
import threading

import numpy as np
import pytest
import viser
from conftest import wait_until

from comms.schema import TrafficSource
from comms.session import embedded_peer, embedded_router, free_tcp_port
from comms.traffic import TrafficTrack
from groundstation.palette import TRAFFIC_RGB
from groundstation.scene import FleetScene, SceneConfig
from groundstation.tables import traffic_table
from tools.intruder_cli import IntruderConfig, intruder_main

TRACK = TrafficTrack(0x2000001, (10.0, -4.0, -6.0), (0.0, 2.0, 0.0), TrafficSource.SIM, True, 0.0)


@pytest.fixture
def server():
    srv = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    yield srv
    srv.stop()


def test_traffic_is_drawn_labelled_moved_and_removed(server) -> None:
    scene = FleetScene(server, SceneConfig(separation_m=3.0, traffic_separation_m=6.0))
    scene.update_traffic([TRACK], 0.5)
    nodes = scene.traffic[0x2000001]
    assert server.scene.get_handle_by_name("/traffic/33554433/body") is not None
    # dead-reckoned 0.5 s east at 2 m/s; scene frame is ENU: (east, north, up)
    assert tuple(nodes["body"].position) == pytest.approx((-3.0, 10.0, 6.0))
    assert nodes["label"].text == "TRF 2000001 SIM manned 2.0m/s 6m 0.5s"
    assert tuple(int(c) for c in nodes["body"].color) == TRAFFIC_RGB
    scene.update_traffic([TRACK], 1.5)
    assert tuple(nodes["body"].position) == pytest.approx((-1.0, 10.0, 6.0))
    scene.update_traffic([], 2.0)
    assert scene.traffic == {} and server.scene.get_handle_by_name("/traffic/33554433/body") is None


def test_traffic_table_lists_tracks_and_flags_stale_ones() -> None:
    html = traffic_table([TRACK], 3.0)
    assert "2000001" in html and "sim manned" in html and "6.0" in html
    assert "color:#e61e1e" in html  # 3 s old: the age is red
    assert "no traffic" in traffic_table([], 0.0)


@pytest.mark.browser
@pytest.mark.e2e
def test_station_shows_an_intruder_in_real_chromium() -> None:
    from test_gcs_browser import CHROMIUM, CHROMIUM_ARGS

    from groundstation.station import GcsConfig, GroundStation

    sync_api = pytest.importorskip("playwright.sync_api")
    port = free_tcp_port()
    stop = threading.Event()
    icfg = IntruderConfig(
        mesh=embedded_peer(port, fleet="trfgcs"),
        from_ne_m=(0.0, -15.0),
        to_ne_m=(0.0, 15.0),
        speed_m_s=1.0,
        alt_m=5.0,
        manned=True,
        start_delay_s=120.0,
    )
    flyer = threading.Thread(target=intruder_main, args=(icfg, stop), kwargs={"out": print})
    with GroundStation(GcsConfig(mesh=embedded_router(port, fleet="trfgcs"), port=0)) as gcs:
        flyer.start()
        try:
            assert wait_until(lambda: len(gcs.traffic) == 1, 20)
            with sync_api.sync_playwright() as p:
                browser = p.chromium.launch(
                    executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS
                )
                page = browser.new_page(viewport={"width": 1200, "height": 800})
                page.set_default_timeout(60_000)
                page.goto(gcs.url)
                page.get_by_text("Traffic (not cooperating)").wait_for()
                page.get_by_text("sim manned").first.wait_for(state="visible")
                assert page.get_by_text("2000001").count() >= 1
                assert wait_until(lambda: 0x2000001 in gcs.scene.traffic, 10)
                # the magenta diamond is on screen: the camera looks at the origin, it is 15 m west
                page.locator("canvas").first.wait_for()
                page.wait_for_timeout(2000)
                png = page.locator("canvas").first.screenshot()
                browser.close()
        finally:
            stop.set()
            flyer.join(10)
    from PIL import Image

    rgb = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), np.int16)
    magenta = (rgb[..., 0] > 150) & (rgb[..., 1] < 90) & (rgb[..., 2] > 100)
    assert magenta.sum() > 20, magenta.sum()


def test_foxglove_draws_a_traffic_report_in_the_scene() -> None:
    from test_foxglove import proto_class

    from comms import keys
    from comms.schema import Role, TrafficFlag, TrafficReport
    from recording import foxglove_channels as fc

    conv = fc.Converter()
    r = TrafficReport(
        Role.STATION,
        2,
        0x2000001,
        TrafficSource.SIM,
        5,
        (10.0, -4.0, -6.0),
        (0.0, 2.0, 0.0),
        1,
        TrafficFlag.MANNED,
    )
    (out,) = conv.convert(keys.gcs_traffic("f", 2), r.encode(), 7)
    assert out.topic == "/scene"
    (ent,) = proto_class("foxglove.SceneUpdate", fc.SCENE_UPDATE.data).FromString(out.data).entities
    assert ent.id == "traffic/2/33554433" and ent.frame_id == "ned"
    assert ent.texts[0].text == "TRF 2000001 SIM manned"
    p = ent.spheres[0].pose.position
    assert (p.x, p.y, p.z) == pytest.approx((10.0, -4.0, -6.0))
    c = ent.spheres[0].color
    assert (round(c.r * 255), round(c.g * 255), round(c.b * 255)) == TRAFFIC_RGB
    assert ent.arrows[0].shaft_length == pytest.approx(2.0)
