"""`papl-map info MAP`: a summary of a map file."""

from __future__ import annotations

import argparse
import json

from papl_mapper.map import Map, map_file
from papl_mapper.palette import axis_names
from papl_mapper.scale.estimate import units_note


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("info", help="summarise a map file", description=__doc__)
    p.add_argument("map", help="a .papl map file, or a run folder holding map.papl")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    m = Map.load(map_file(args.map))
    s = m.summary()
    s["units_note"] = units_note(m.metadata)
    s["scale"] = m.metadata.get("scale")
    if args.json:
        print(json.dumps(s, indent=2))
        return 0
    names = axis_names(len(m.axes), m.axes.vertical_index)
    cam = m.camera
    print(f"map            {args.map}")
    print(
        f"camera         {cam.width}x{cam.height}  "
        f"fx={cam.fx:.2f} fy={cam.fy:.2f} cx={cam.cx:.2f} cy={cam.cy:.2f}"
    )
    print(f"keyframes      {s['keyframes']}")
    if "trajectory_length" in s:
        print(f"trajectory     {s['trajectory_length']:.3f} {s['units']} over {s['duration_s']:.2f} s")
    print(f"points         {s['points']}  ({s['point_observations']} observations)")
    print(f"lines          {s['lines']}  ({s['line_observations']} observations)")
    print(f"anchored       {100 * s['anchored_fraction']:.1f} %  ({s['unanchored_lines']} unanchored)")
    print(f"units          {units_note(m.metadata)}")
    print(f"axes           {len(m.axes)}")
    for a, (name, d) in enumerate(zip(names, m.axes.directions, strict=True)):
        print(f"  {a}  {name:<13} ({d[0]:+.4f}, {d[1]:+.4f}, {d[2]:+.4f})  {s['lines_per_axis'][a]} lines")
    if len(m.axes) > 1:
        ang = m.axes.angles_deg()
        pairs = [f"{i}-{j}: {ang[i, j]:.2f}°" for i in range(len(m.axes)) for j in range(i + 1, len(m.axes))]
        print("axis angles    " + ", ".join(pairs))
    return 0
