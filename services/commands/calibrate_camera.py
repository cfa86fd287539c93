"""semloc calibrate-camera SOURCE -o camera.yml: calibrate a camera from views of a chessboard (docs/camera.md).

SOURCE is anything the camera worker reads (a video, an image folder, a device index, a URL, a bag...). Every
``--every``-th frame is searched for the whole board (``--board`` inner corners, ``--square`` metres), kept when it
moved ``--min-move`` from every view kept; at the end of a file (``--views`` of them spread over it) or once a live
source gave ``--views``, OpenCV fits a pinhole (plumb_bob distortion) or fisheye (equidistant) model, and the
calibration file the camera worker reads (``calibration:``) is written with its reprojection error, e.g.

  semloc calibrate-camera board.mp4 -o deploy/local/camera.yml --board 9x6 --square 0.025
  semloc calibrate-camera 0 -o camera.yml --model fisheye      # a live device: move the board around
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from services.commands import fail, logger, print_json

DEFAULT_VIEWS = 40
DEFAULT_MIN_MOVE = 0.02  # of the image's diagonal: a view is kept when its corners moved this much from every other


def board_size(text: str) -> tuple[int, int]:
    match = re.fullmatch(r"(\d+)[xX](\d+)", text.strip())
    if not match:
        raise argparse.ArgumentTypeError(f"expected COLUMNSxROWS inner corners, e.g. 9x6, got {text!r}")
    return int(match.group(1)), int(match.group(2))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("source", help="video, image folder, device index, URL, bag... (as the camera worker's)")
    parser.add_argument("-o", "--output", required=True, help="calibration YAML to write (the camera worker's "
                                                              "calibration: file)")
    parser.add_argument("--board", type=board_size, default=(9, 6), metavar="COLSxROWS",
                        help="the chessboard's inner corners (default 9x6)")
    parser.add_argument("--square", type=float, default=0.025, metavar="M", help="square size in metres "
                                                                                  "(default 0.025)")
    parser.add_argument("--model", choices=("pinhole", "fisheye"), default="pinhole",
                        help="pinhole with OpenCV's 5 distortion coefficients (default), or fisheye (equidistant)")
    parser.add_argument("--every", type=int, default=1, metavar="N", help="search every N-th frame (default 1)")
    parser.add_argument("--views", type=int, default=DEFAULT_VIEWS, metavar="N",
                        help=f"views to fit: spread over a file, the first N of a live source "
                             f"(default {DEFAULT_VIEWS})")
    parser.add_argument("--min-move", type=float, default=DEFAULT_MIN_MOVE, metavar="F",
                        help="keep a view only when its corners moved on average at least F x the image's diagonal "
                             f"from every view kept (default {DEFAULT_MIN_MOVE}; 0 keeps every view)")
    parser.add_argument("--source-type", default="auto", help="as the camera worker's source_type (default auto)")
    parser.add_argument("--name", default="front", help="camera_name in the file (default front)")
    parser.add_argument("--json", action="store_true", help="print the result as JSON on stdout")
    parser.add_argument("--quiet", action="store_true", help="no progress on stderr")


def run(args: argparse.Namespace) -> int:
    import itertools

    import numpy as np
    import yaml

    from semloc_core.camera_calibration import MIN_VIEWS, Chessboard, calibrate, find_corners, new_view
    from semloc_core.io.errors import FileFormatError
    from semloc_core.io.camera_model import camera_to_mapping
    from services.camera_sources import SourceError, open_source

    say = logger(args.quiet)
    try:
        board = Chessboard(*args.board, square_m=args.square)
        if args.every < 1 or args.views < 1:
            raise ValueError("--every and --views must be at least 1")
        if not 0 <= args.min_move < 1:
            raise ValueError(f"--min-move is a fraction of the image's diagonal in [0, 1), got {args.min_move}")
        source = open_source(args.source, args.source_type)
        source.on_skip = lambda _why, detail: say(detail)  # an unreadable frame is one view fewer, no more
    except (ValueError, FileFormatError) as error:
        return fail("calibrate-camera", error)
    corners, size, frames, boards = [], None, 0, 0
    try:
        for capture in itertools.islice(source, 0, None, args.every):
            frames += 1
            image = capture.images[0]
            if size is None:
                size = (image.shape[1], image.shape[0])
            elif (image.shape[1], image.shape[0]) != size:
                raise ValueError(f"frame {frames * args.every - args.every} is {image.shape[1]}x{image.shape[0]}, "
                                 f"the first {size[0]}x{size[1]}")
            found = find_corners(image, board)
            kept = found is not None and new_view(found, corners, args.min_move * float(np.hypot(*size)))
            boards += found is not None
            if kept:
                corners.append(found)
            say(f"frame {frames * args.every - args.every}: "
                f"{'no board' if found is None else 'board' if kept else 'board, too close to a view kept'} "
                f"({len(corners)}/{args.views} views)")
            if source.live and len(corners) >= args.views:
                break
        if size is None:
            raise ValueError(f"no frame in {args.source}")
        if len(corners) > args.views:  # a file read to its end: views spread over all of it
            corners = [corners[int(i)] for i in np.linspace(0, len(corners) - 1, args.views).round()]
        if len(corners) < MIN_VIEWS:
            close = boards - len(corners)
            raise ValueError(f"{len(corners)} view(s) of a {board.columns}x{board.rows} chessboard (inner corners, "
                             f"--board) in {frames} frame(s) searched"
                             + (f", {close} more too close to a view kept (--min-move)" if close else "")
                             + f": at least {MIN_VIEWS} are needed; show the board whole, at several angles and "
                               f"distances")
        result = calibrate(corners, board, *size, model=args.model)
    except (ValueError, SourceError) as error:  # SourceError: a live source that stopped
        return fail("calibrate-camera", error)
    finally:
        source.close()
    document = camera_to_mapping(result.camera, args.name)
    document["reprojection_error_px"] = round(result.rms_px, 4)
    document["views"] = result.views
    output = Path(args.output)
    output.parent.mkdir(parents=True, exist_ok=True)
    output.write_text(yaml.safe_dump(document, sort_keys=False))
    K = result.camera.K
    summary = {"output": str(output), "model": args.model, "width": size[0], "height": size[1], "views": result.views,
               "frames_read": frames, "boards_seen": boards, "reprojection_error_px": result.rms_px,
               "fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "dist": result.camera.dist.tolist()}
    if args.json:
        print_json(summary)
    else:
        print(f"{args.model} {size[0]}x{size[1]} from {result.views} views: fx={K[0, 0]:.2f} fy={K[1, 1]:.2f} "
              f"cx={K[0, 2]:.2f} cy={K[1, 2]:.2f}, reprojection error {result.rms_px:.3f} px RMS; wrote {output}")
    return 0
