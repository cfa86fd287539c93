"""``semloc map save DIR``: ask a running graph for its maps and write them to DIR, the files ``semloc up --save``
writes (objects.json, voxels.npz, voxels.ply, topomap.json, topomap.graphml; docs/conventions.md, "Files and their
frames"). Prints one line; exits 1 when nothing answered.

  semloc map save maps/ --hub tcp/192.168.1.20:7447
"""

from __future__ import annotations

import sys

from schemas.keys import DEFAULT_ROBOT
from semloc_core.validation import one_line
from services.bus import add_bus_arguments, bus_from_args, open_session
from services.commands import fail


def add_arguments(parser) -> None:
    actions = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    save = actions.add_parser("save", help="write the mapper's and the loop closure's maps to DIR",
                              description=__doc__.strip())
    save.add_argument("folder", metavar="DIR", help="where the files go (created)")
    save.add_argument("--robot", default=DEFAULT_ROBOT,
                      help=f"the robot's namespace (default {DEFAULT_ROBOT}, the deploy graphs')")
    save.add_argument("--wait", type=float, default=5.0, help="seconds to wait for the workers to answer")
    save.add_argument("--hot-fraction", type=float, metavar="F",
                      help="voxels.ply: voxels scoring at least F of their class's best (default: --save's)")
    add_bus_arguments(save)


def run(args) -> int:
    from schemas import FrameError, keys
    from schemas.loopclosure import TopoMap
    from schemas.mapping import VoxelMap
    from services.bus import QueryError, ask
    from services.saving import HOT_FRACTION, write_maps

    fraction = HOT_FRACTION if args.hot_fraction is None else args.hot_fraction
    if not 0 < fraction <= 1:
        return fail("map save", f"--hot-fraction must be in (0, 1], got {fraction}")
    mapper_key, topomap_key = keys.mapper_save(args.robot), keys.loopclosure_topomap(args.robot)
    with open_session(bus_from_args(args)) as session:
        try:  # ask() asks again until the new session has met the workers
            voxel_maps = ask(session, mapper_key, reply_type=VoxelMap, wait=args.wait)
            topomaps = ask(session, topomap_key, reply_type=TopoMap, wait=args.wait if not voxel_maps else 1.0)
        except (QueryError, FrameError) as error:
            print(f"semloc map save: {one_line(error)}", file=sys.stderr, flush=True)
            return 1
    voxel_map, topomap = (voxel_maps or [None])[0], (topomaps or [None])[0]
    if voxel_map is None and topomap is None:
        print(f"semloc map save: nothing answered on {mapper_key} or {topomap_key} in {args.wait:g} s",
              file=sys.stderr, flush=True)
        return 1
    try:
        written = write_maps(args.folder, voxel_map, topomap, fraction)
    except OSError as error:  # a full or read-only disk: the files written before it are whole
        print(f"semloc map save: cannot write {error.filename}: {error.strerror}", file=sys.stderr, flush=True)
        return 1
    missing = [name for name, frame in (("mapper", voxel_map), ("loop closure", topomap)) if frame is None]
    print(f"saved {len(written)} files to {args.folder}: "
          + (f"{len(voxel_map.class_index)} objects over {voxel_map.frames} frames" if voxel_map else "no object map")
          + (f", {len(topomap.keyframes)} places" if topomap else "")
          + (f" (no answer from the {' or '.join(missing)})" if missing else ""))
    return 0
