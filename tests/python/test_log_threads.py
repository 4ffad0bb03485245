"""Reading logs from several threads at once leaves file descriptor 2 where
it was. read_log captures what liblcm prints on fd 2 by pointing fd 2 at a
temporary file; the experiments read each finished run's log in a worker
thread, and two unserialised captures restored each other's saved
descriptor, which left fd 2 on a deleted temporary file for the rest of the
run (seen: a `--full` run's progress and final lines vanished after 8 min)."""

from __future__ import annotations

import os
import threading
from ftc.plant.log import read_log


def test_concurrent_reads_leave_fd_2_alone(tmp_path, write_state_log):
    path = tmp_path / "run.lcmlog"
    write_state_log(path, 200, drop_per_step=0.001)
    before = os.fstat(2)
    errors: list[BaseException] = []

    def reader() -> None:
        try:
            for _ in range(60):
                assert len(read_log(path)) == 200
        except BaseException as e:  # noqa: BLE001 - reported by the main thread
            errors.append(e)

    threads = [threading.Thread(target=reader) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    after = os.fstat(2)
    assert not errors, errors
    assert (after.st_dev, after.st_ino) == (before.st_dev, before.st_ino)
