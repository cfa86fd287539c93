"""The engine's store on a disk that fills up: the frame that does not fit is an OSError naming the store's file,
the frames stored before it stay as they were (not a SIGBUS killing the process at its first write into a page the
file system cannot back). Runs in a private mount namespace on a 1 MiB tmpfs; skipped where one cannot be made (not
root, no ``unshare``)."""

from __future__ import annotations

import shutil
import subprocess
import sys
import textwrap

import pytest

FILL = textwrap.dedent("""
    import errno, sys
    import numpy as np
    from semloc_core.io.loopclosure import FileStorage
    from semloc_core.loopclosure.matching import DESCRIPTOR_SIZE, FrameStore

    store = FrameStore(2, FileStorage(sys.argv[1] + "/store"))
    rng = np.random.default_rng(0)
    frames = [rng.integers(0, 256, (500, DESCRIPTOR_SIZE), dtype=np.uint8) for _ in range(40)]
    for k, descriptors in enumerate(frames):
        try:
            store.add(descriptors, np.zeros(len(descriptors)))
        except OSError as error:
            assert error.errno == errno.ENOSPC and "/store/" in error.filename, error
            assert len(store) == k > 0
            assert all(np.array_equal(store.descriptors(f), frames[f]) for f in range(k))
            print("refused", k)
            break
    """)


def test_a_full_disk_refuses_the_frame_that_does_not_fit_and_keeps_the_others(tmp_path):
    if shutil.which("unshare") is None:
        pytest.skip("no unshare")
    probe = subprocess.run(["unshare", "-m", "sh", "-c", f"mount -t tmpfs -o size=1m tmpfs {tmp_path}"],
                           capture_output=True)
    if probe.returncode != 0:
        pytest.skip(f"no private tmpfs here: {probe.stderr.decode().strip()}")
    mounted = 'mount -t tmpfs -o size=1m tmpfs "$0" && exec "$1" -c "$2" "$0"'
    done = subprocess.run(["unshare", "-m", "sh", "-c", mounted, str(tmp_path), sys.executable, FILL],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, (done.returncode, done.stderr[-2000:])
    assert done.stdout.startswith("refused "), done.stdout
