"""``gonio sim serve`` prints the ports it serves and the commands that reach them with the real
paths (issue 40: it printed `--port ZABER --meter-port METER --camera CAMERA` placeholders), and
the hints work: the printed PyVISA resource answers *IDN?."""

import signal
import subprocess
import sys
import time

import pytest

pytestmark = pytest.mark.timeout(120)


def test_serve_prints_real_ports_and_commands():
    p = subprocess.Popen([sys.executable, "-m", "gonio.cli.main", "sim", "serve", "--clock", "instant"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    lines = []
    try:
        deadline = time.monotonic() + 90
        while time.monotonic() < deadline:
            line = p.stdout.readline()
            if not line:
                break
            lines.append(line.rstrip("\n"))
            if "zaber-motion:" in line:
                break
        text = "\n".join(lines)
        ports = {t[0]: (t[1], t[3]) for t in (ln.split() for ln in lines) if len(t) == 4 and t[2] == "->"}
        assert set(ports) == {"zaber", "meter", "camera"}, text
        for word in ("ZABER", "METER", "CAMERA"):
            assert word not in text, text
        z, m, c = (ports[k][0] for k in ("zaber", "meter", "camera"))
        assert f"gonio capture --port {z} --meter-port {m} --camera {c}" in text, text
        resource = f"ASRL{ports['meter'][1]}::INSTR"
        assert resource in text, text
        pyvisa = pytest.importorskip("pyvisa")
        rm = pyvisa.ResourceManager("@py")
        r = rm.open_resource(resource, read_termination="\n", write_termination="\n", timeout=5000)
        assert r.query("*IDN?").startswith("Thorlabs,PM100D,")
        r.close()
        rm.close()
    finally:
        p.send_signal(signal.SIGTERM)
        out, err = p.communicate(timeout=30)
    assert p.returncode == 0 and "stopped" in out, (p.returncode, out, err)
