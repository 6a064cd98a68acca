"""The simulated devices trust nothing they are sent (issue 36, items 1 and 5).

A command line holding a control character is refused by each protocol's own error and
nothing of it executed; a line longer than the protocol's bound is answered with its error
and discarded, its bytes never buffered past the bound; replies a host never reads wait in a
bounded buffer; the camera writes nowhere but in the folder it serves.
"""

import os
import tracemalloc

import pytest

from gonio.sim.devices import port as _port

CONTROLS = ["\n", "\r", "\x00", "\x1b", "\x85"]


def _line(port, text, end=b"\n"):
    port.write(text.encode("utf-8") + end)
    return port.readline().decode("utf-8").strip()


# --------------------------------------------------------------------------- control characters
@pytest.mark.parametrize("ch", ["\x00", "\x1b", "\x1f", "\x85", "\t", "\u2028"])
def test_camera_refuses_control_characters(make, tmp_path, ch):
    inst = make()
    c = inst.open("camera", timeout=0.5)
    assert _line(c, f"EXPOSE 0.001 {tmp_path}/a{ch}b.dng") == "ERR control character"
    assert _line(c, f"EXPOSE{ch}0.001 {tmp_path}/x.dng") == "ERR control character"
    assert os.listdir(tmp_path) == []
    assert _line(c, f"EXPOSE 0.001 {tmp_path}/ok.dng").startswith("OK ")      # the next line is read
    assert inst.camera.handle(f"EXPOSE 0.001 {tmp_path}/b{ch}.dng") == ["ERR control character"]
    assert os.listdir(tmp_path) == ["ok.dng"]


def test_zaber_refuses_control_characters(make):
    inst = make()
    z = inst.open("zaber", timeout=0.5)
    # \x1f split the words before: "home\x1fx" homed; \x00 and ESC made unknown words
    for ch in ("\x1f", "\x00", "\x1b", "\x0b"):
        reply = _line(z, f"/1 0 home{ch}", end=b"\r\n")
        assert reply.startswith("@01 0 RJ") and reply.endswith("BADDATA"), reply
    assert _line(z, "/1 0", end=b"\r\n") == "@01 0 OK IDLE WR 0"                  # still not homed


def test_meter_refuses_control_characters(make):
    inst = make()
    m = inst.open("meter", timeout=0.5)
    # \x1f split header and argument before: the wavelength was set to 700
    for ch in ("\x1f", "\x00", "\x1b", "\x0b"):
        m.write(f"SENS:CORR:WAV{ch}700\n".encode())
        assert _line(m, "SYST:ERR?") == '-101,"Invalid character"'
    assert float(_line(m, "SENS:CORR:WAV?")) == pytest.approx(inst.scpi.WAV_DEFAULT)


# --------------------------------------------------------------------------- overlong lines
def test_overlong_lines_are_answered_and_discarded(make, tmp_path):
    inst = make()
    c, z, m = (inst.open(p, timeout=0.5) for p in ("camera", "zaber", "meter"))
    cam = inst.ports["camera"]
    # a camera line that goes on and on, in chunks: never buffered past the bound
    c.write(f"EXPOSE 0.001 {tmp_path}/".encode())
    for _ in range(64):
        c.write(b"a" * 65536)
        assert len(cam._in) <= cam.max_line == inst.camera.MAX_LINE
    c.write(b".dng\n")
    assert c.readline() == b"ERR line too long\n"
    assert os.listdir(tmp_path) == []
    assert _line(c, "*IDN?") == inst.camera.IDN                                  # the next line is whole
    # Zaber: the addressed device rejects it, nothing executed
    reply = _line(z, "/1 0 home " + "x" * 1000, end=b"\r\n")
    assert reply.startswith("@01 0 RJ") and reply.endswith("BADDATA"), reply
    assert _line(z, "/1 0", end=b"\r\n") == "@01 0 OK IDLE WR 0"
    assert len(inst.ports["zaber"]._in) == 0
    # SCPI: error -363, no response, nothing executed
    m.write(b"SENS:CORR:WAV 700;" + b"*CLS;" * 1000 + b"\n")
    assert _line(m, "SYST:ERR?") == '-363,"Input buffer overrun"'
    assert float(_line(m, "SENS:CORR:WAV?")) == pytest.approx(inst.scpi.WAV_DEFAULT)
    # a line of exactly the bound still runs
    assert inst.scpi.handle("*IDN?" + " " * (inst.scpi.MAX_LINE - 5)) == [inst.scpi.IDN]


def test_flooding_without_a_newline_keeps_memory_bounded(make):
    inst = make()
    c = inst.open("meter", timeout=0.5)
    chunk = b"x" * (1 << 20)
    c.write(chunk)                                        # warm up whatever a first write allocates
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        for _ in range(32):                               # 32 MiB that never end a line
            c.write(chunk)
        grown = tracemalloc.get_traced_memory()[0] - base
    finally:
        tracemalloc.stop()
    assert grown < (1 << 20), grown
    assert len(inst.ports["meter"]._in) <= inst.scpi.MAX_LINE


def test_flooding_without_reading_keeps_replies_bounded(make):
    inst = make()
    c = inst.open("camera", timeout=0.5)
    ep = inst.ports["camera"]
    for _ in range(4):
        c.write(b"*IDN?\n" * 5000)                        # 20000 replies, none read
        assert len(ep.out) <= 1 << 16                    # port.MAX_OUT
    assert ep.overrun > 0 and _port.MAX_OUT == 1 << 16
    assert ep.commands == 20000
    c.reset_input_buffer()
    assert _line(c, "SENSOR?").endswith("RGGB")           # once read, the port answers again


# --------------------------------------------------------------------------- the camera's folder
def test_camera_writes_only_in_its_folder(make, tmp_path):
    inst = make()
    c = inst.open("camera", timeout=0.5)
    served = tmp_path / "session"
    (served / "raw").mkdir(parents=True)
    outside = tmp_path / "outside"
    outside.mkdir()
    victim = tmp_path / "victim"
    victim.write_text("precious")
    (served / "out").symlink_to(outside)                  # a link out of the folder
    (served / "raw" / "link.dng").symlink_to(victim)      # a link at the file's own name
    inst.camera.root = served
    refused = "ERR path outside the camera folder"
    for path in (victim, served / ".." / "victim", "../victim", served / "raw" / ".." / ".." / "victim",
                 served / "out" / "x.dng", served / "raw" / "link.dng", served, "/etc/gonio-x.dng"):
        assert _line(c, f"EXPOSE 0.001 {path}") == refused, path
        assert _line(c, f"FLAT 0.001 {path}") == refused, path
    assert victim.read_text() == "precious" and os.listdir(outside) == []
    assert _line(c, f"EXPOSE 0.001 {served}/raw/a.dng").startswith("OK ")
    assert _line(c, "CHART 0.001 raw/b.dng").startswith("OK ")        # relative: inside the folder
    assert sorted(os.listdir(served / "raw")) == ["a.dng", "b.dng", "link.dng"]


def test_camera_without_a_folder_refuses_dotdot(make, tmp_path):
    inst = make()
    c = inst.open("camera", timeout=0.5)
    (tmp_path / "a").mkdir()
    assert _line(c, f"EXPOSE 0.001 {tmp_path}/a/../x.dng") == "ERR path outside the camera folder"
    assert _line(c, f"EXPOSE 0.001 {tmp_path}/a/x.dng").startswith("OK ")
    assert sorted(os.listdir(tmp_path)) == ["a"]
