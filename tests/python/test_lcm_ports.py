"""Private LCM ports stay out of the kernel's ephemeral range, and a port
that is taken anyway is a clear error, not a crash.

Seen in CI: an experiment's recorder drew a port that another process held as
an ephemeral (outgoing) UDP port; liblcm printed "bind: Address already in
use" and the recorder died with SIGSEGV on its first subscription."""

from __future__ import annotations

import socket
import subprocess

import pytest

from ftc.common.build_info import echo_binary, plant_binary, recorder_binary
from ftc.plant.lcm_link import private_lcm_url, private_port_range


@pytest.mark.parametrize("text,expected", [("32768\t60999\n", range(20000, 32768)),
                                           ("40000 60999", range(20000, 40000)),
                                           ("21000 60999", range(20000, 32768)),
                                           ("garbage", range(20000, 32768))])
def test_private_ports_are_below_the_ephemeral_range(tmp_path, text, expected):
    path = tmp_path / "ip_local_port_range"
    path.write_text(text)
    assert private_port_range(str(path)) == expected
    assert private_port_range(str(tmp_path / "missing")) == range(20000, 32768)


def test_private_urls_use_this_kernels_range():
    with open("/proc/sys/net/ipv4/ip_local_port_range") as f:
        low = int(f.read().split()[0])
    ports = {int(private_lcm_url().split(":")[2].split("?")[0]) for _ in range(300)}
    assert all(20000 <= p < low for p in ports) and len(ports) > 250



def test_an_orchestrator_never_gives_two_recent_runs_one_url(monkeypatch):
    # 24 parallel runs once drew the same port twice (2% for independent draws);
    # with only ten ports to draw from, ten runs in a row still get ten.
    from ftc.experiments import runs
    from ftc.plant import lcm_link

    monkeypatch.setattr(lcm_link, "private_port_range", lambda: range(20000, 20010))
    monkeypatch.setattr(runs, "_recent_urls", runs.deque(maxlen=9))
    urls = [runs.run_url() for _ in range(30)]
    for i in range(len(urls) - 9):
        assert len(set(urls[i:i + 10])) == 10, urls[i:i + 10]

@pytest.mark.parametrize("binary,args", [(recorder_binary, ["out.lcmlog"]), (plant_binary, []),
                                         (echo_binary, [])], ids=["recorder", "plant", "echo"])
def test_a_taken_port_is_a_clear_error(tmp_path, binary, args):
    taken = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # no SO_REUSEADDR: not shared
    taken.bind(("0.0.0.0", 0))
    url = f"udpm://239.255.76.67:{taken.getsockname()[1]}?ttl=0"
    try:
        proc = subprocess.run([str(binary()), "--lcm-url", url, *args], cwd=tmp_path,
                              capture_output=True, text=True, timeout=30)
    finally:
        taken.close()
    assert proc.returncode > 0, (proc.returncode, proc.stderr)  # an exit code, not a signal
    assert f"cannot receive on '{url}'" in proc.stderr.splitlines()[-1]
