"""``semloc export SESSION.mcap -o DIR``: a recorded session (``semloc record``) as the files ``semloc up --save``
writes: trajectory.tum, groundtruth.tum, objects.json (the last object map), topomap.json and topomap.graphml
(rebuilt from the map's updates). The voxel map is not on the bus: ``semloc map save`` writes it during a run.
Frames of each file: docs/conventions.md, "Files and their frames".

  semloc export session.mcap -o session/ && evo_ape tum session/groundtruth.tum session/trajectory.tum
"""

from __future__ import annotations

from schemas.keys import DEFAULT_ROBOT
from services.commands import fail


def add_arguments(parser) -> None:
    parser.add_argument("session", metavar="SESSION.mcap", help="a recording (semloc record; or its folder of splits)")
    parser.add_argument("-o", "--output", required=True, metavar="DIR", help="where the files go (created)")
    parser.add_argument("--robot", default=DEFAULT_ROBOT,
                        help=f"the robot whose streams to export (default {DEFAULT_ROBOT})")


def run(args) -> int:
    from pathlib import Path

    from services.recording import is_robot_log, is_split_recording
    from services.saving import export_recording

    if Path(args.session).exists() and is_robot_log(args.session):  # its images, not the workers' results
        return fail("export", f"{args.session} is a robot log, not a semloc recording: play it into a graph "
                              "(semloc replay) while semloc record writes one, and export that")
    if not Path(args.session).is_file() and not is_split_recording(args.session):
        return fail("export", f"no such recording: {args.session}")
    try:
        counts = export_recording(args.session, args.output, args.robot)
    except (OSError, ValueError) as error:  # a file that is not a recording: CutFileError
        return fail("export", error)
    written = {name: count for name, count in counts.items() if "." in name or name == "topomap_nodes"}
    if not written:
        return fail("export", f"{args.session} holds none of robot {args.robot}'s poses, object maps or "
                              f"topological map ({counts['messages']} of its messages read)")
    print(f"exported {args.session} to {args.output}: " + ", ".join(f"{name} {count}" for name, count in
                                                                   written.items()))
    return 0
