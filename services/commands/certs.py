"""``semloc certs DIR --robot NAME``: a development CA and the certificates of deploy/secure/ (docs/security.md).

For development and trials only: production deployments bring their own PKI (docs/security.md says what each
certificate must hold).
"""

from __future__ import annotations

import sys

from services.certs import DEFAULT_DAYS, write_layout


def add_arguments(parser) -> None:
    parser.add_argument("directory", metavar="DIR", help="where the CA and the certificates go (created if needed)")
    parser.add_argument("--robot", required=True, help="the robot's name (its router's and workers' identities)")
    parser.add_argument("--base-host", action="append", default=[], metavar="HOST",
                        help="a name or address the base station's router is reached at (repeatable; loopback "
                             "names are always there)")
    parser.add_argument("--robot-host", action="append", default=[], metavar="HOST",
                        help="a name or address the robot's router is reached at (repeatable)")
    parser.add_argument("--days", type=int, default=DEFAULT_DAYS,
                        help=f"validity of the certificates issued (default {DEFAULT_DAYS})")
    parser.add_argument("--renew", action="append", default=[], metavar="NAME",
                        help="issue this identity again with a new key (rotation; repeatable), e.g. operator")


def run(args) -> int:
    try:
        written = write_layout(args.directory, args.robot, base_hosts=args.base_host, robot_hosts=args.robot_host,
                               days=args.days, renew=tuple(args.renew))
    except (ValueError, OSError) as error:
        print(f"semloc certs: {error}", file=sys.stderr)
        return 2
    width = max(len(str(w.path)) for w in written)
    print(f"development certificates in {args.directory} (not for production: docs/security.md)")
    for entry in written:
        print(f"  {entry.action:8s} {str(entry.path):{width}s}  {entry.where}")
    print("each NAME.pem goes with its NAME-key.pem (owner-only); ca.pem goes everywhere, ca-key.pem nowhere")
    return 0
