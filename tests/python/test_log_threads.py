"""Reading logs from several threads at once leaves file descriptor 2 where
it was. read_log captures what liblcm prints on fd 2 by pointing fd 2 at a
temporary file; the experiments read each finished run's log in a worker
thread, and two unserialised captures restored each other's saved
descriptor, which left fd 2 on a deleted temporary file for the rest of the
run (seen: a `--full` run's progress and final lines vanished after 8 min)."""

from __future__ import annotations

import os
import threading
from pathlib import Path

from ftc.plant.log import read_log


def _write_log(path: Path, steps: int) -> None:
    import lcm

    from ftc.plant_state_t import plant_state_t

    log = lcm.EventLog(str(path), "w", overwrite=True)
    for k in range(steps + 1):
        m = plant_state_t()
        m.seq, m.command_seq, m.episode, m.step = k + 1, k, 0, k
        m.num_tanks, m.num_engines = 6, 2
        m.level = m.true_level = [1.0 - 0.001 * k] * 6
        m.valve = [0] * 6
        m.deficit = [0.0, 0.0]
        log.write_event(1000 + k, "T_STATE", m.encode())
    log.close()


def test_concurrent_reads_leave_fd_2_alone(tmp_path):
    path = tmp_path / "run.lcmlog"
    _write_log(path, 200)
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
