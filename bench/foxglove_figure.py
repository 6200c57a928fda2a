"""Draw a recording's standard Foxglove channels with matplotlib, as the docs layout shows them
(3D from above, Map, Plot, Log): `python -m bench.foxglove_figure flight.mcap [-o PNG]`.

A stand-in for a Foxglove screenshot, which cannot be taken here. It reads only the standard
channels, decoded with protobuf from the schemas in the file, so it shows what Foxglove gets.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from mcap.reader import make_reader

from bench.common import DOCS, pyplot
from bench.foxglove import proto_class


def read_standard(path: str | Path) -> dict[str, list[tuple[int, object]]]:
    """topic -> [(log_time_ns, decoded message)] for the protobuf and JSON channels."""
    out: dict[str, list] = {}
    classes: dict[int, object] = {}
    with open(path, "rb") as f:
        for sch, ch, msg in make_reader(f).iter_messages():
            if ch.message_encoding == "protobuf":
                if sch.id not in classes:
                    classes[sch.id] = proto_class(sch.name, sch.data)
                out.setdefault(ch.topic, []).append(
                    (msg.log_time, classes[sch.id].FromString(msg.data))
                )
            elif ch.message_encoding == "json":
                out.setdefault(ch.topic, []).append((msg.log_time, json.loads(msg.data)))
    return out


def main(path: str, out_png: Path) -> Path:
    std = read_standard(path)
    plt = pyplot()
    fig, ((ax3d, axmap), (axplot, axlog)) = plt.subplots(2, 2, figsize=(12, 9))
    vids = sorted(int(t.split("/")[2]) for t in std if t.endswith("/pose"))
    t0 = min(ts for t in std for ts, _ in std[t])
    for vid in vids:
        poses = [m.pose.position for _, m in std[f"/vehicles/{vid}/pose"]]
        times = [(ts - t0) / 1e9 for ts, _ in std[f"/vehicles/{vid}/pose"]]
        (line,) = ax3d.plot(
            [p.y for p in poses], [p.x for p in poses], lw=1, label=f"vehicle {vid}"
        )
        fixes = [m for _, m in std[f"/vehicles/{vid}/fix"]]
        axmap.plot(
            [f.longitude for f in fixes], [f.latitude for f in fixes], lw=1, color=line.get_color()
        )
        axplot.plot(times, [-p.z for p in poses], lw=1, color=line.get_color())
    # the last scene entity of each vehicle: body coloured by mode, separation ring
    last = {}
    for _, upd in std.get("/scene", []):
        for ent in upd.entities:
            last[ent.id] = ent
    for ent in last.values():
        cube, ring = ent.cubes[0], ent.cylinders[0]
        c = (cube.color.r, cube.color.g, cube.color.b)
        ax3d.plot(cube.pose.position.y, cube.pose.position.x, "s", color=c, ms=8)
        ax3d.add_patch(plt.Circle((ring.pose.position.y, ring.pose.position.x), ring.size.x / 2,
                                  fill=False, color=(ring.color.r, ring.color.g, ring.color.b)))  # fmt: skip
    ax3d.set(
        title="3D (/scene, /vehicles/*/pose), from above",
        xlabel="east m",
        ylabel="north m",
        aspect="equal",
    )
    ax3d.legend(fontsize=7)
    axmap.set(title="Map (/vehicles/*/fix)", xlabel="longitude deg", ylabel="latitude deg")
    axmap.ticklabel_format(useOffset=False)
    axplot.set(title="Plot: altitude (-pose.position.z)", xlabel="s", ylabel="m")
    lines = [
        f"{(ts - t0) / 1e9:6.1f}s  {m.name:10s} {m.message}" for ts, m in std.get("/events", [])
    ]
    lines += [f"{(ts - t0) / 1e9:6.1f}s  ack vehicle/{a['vehicle_id']} {a['command_kind']} {a['result']}"
              for ts, a in std.get("/acks", [])]  # fmt: skip
    lines.sort()
    axlog.axis("off")
    axlog.set_title("Log (/events) and /acks")
    axlog.text(
        0,
        1,
        "\n".join(lines[:28]),
        va="top",
        family="monospace",
        fontsize=7,
        transform=axlog.transAxes,
    )
    fig.tight_layout()
    fig.savefig(out_png, dpi=80)
    return out_png


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("file")
    ap.add_argument("-o", "--output", type=Path, default=DOCS / "foxglove_view.png")
    a = ap.parse_args()
    print(f"wrote {main(a.file, a.output)}")
