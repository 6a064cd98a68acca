"""Instrument settings: defaults, overrides, one-line errors."""

import pytest

from gonio.bench.settings import default_settings, load_settings, merge_settings
from gonio.core.errors import GonioError


def test_defaults_match_the_contract():
    s = default_settings()
    assert s["axes"]["yaw"] == [1, 1, -95.0, 95.0] and s["axes"]["cycle_dist"] == 720000
    assert s["axes"]["lamp_block_deg"] == 6.0 and s["camera"]["width"] == 64 and s["holder"]["offset"] == 0.3
    assert s["reference"] == {"reflectance": 0.99, "rel_std": 0.005}
    assert load_settings() == s


def test_override_one_table_at_a_time(tmp_path):
    f = tmp_path / "lab.toml"
    f.write_text("[reference]\nreflectance = [0.98, 0.99, 0.97]\n[motion]\nlamp = [10.0, 20.0]\n")
    s = load_settings(f)
    assert s["reference"]["reflectance"] == [0.98, 0.99, 0.97] and s["reference"]["rel_std"] == 0.005
    assert s["motion"]["lamp"] == [10.0, 20.0] and s["motion"]["yaw"] == [20.0, 40.0]
    assert merge_settings(s, {"camera": {"width": 128}})["camera"]["height"] == 48


@pytest.mark.parametrize("text, match", [
    ("[axes\n", "not valid TOML"),
    ("[axes]\ntilt = [1, 2, 88.0, -88.0]\n", "axes.tilt"),
    ("[motion]\nyaw = [0.0, 40.0]\n", "motion.yaw"),
    ("[reference]\nreflectance = -1\n", "reference.reflectance"),
])
def test_bad_settings_are_one_line(tmp_path, text, match):
    f = tmp_path / "bad.toml"
    f.write_text(text)
    with pytest.raises(GonioError, match=match) as e:
        load_settings(f)
    assert "\n" not in str(e.value)
    with pytest.raises(GonioError, match="cannot read settings file"):
        load_settings(tmp_path / "missing.toml")


@pytest.mark.parametrize("text, match", [
    ("[refrence]\nreflectance = 0.5\n", r"unknown section \[refrence\]; did you mean \[reference\]\?"),
    ("[reference]\nreflectanse = 0.5\n", r"unknown key 'reflectanse' in \[reference\]; did you mean reflectance\?"),
    ("[camera]\nwidht = 100\n", r"did you mean width\?"),
    ("[zzz]\nx = 1\n", r"unknown section \[zzz\]; known sections"),
    ("camera = 3\n", r"camera must be a table"),
    ("[session]\noperator = 7\n", r"session.operator must be a line of printable text"),
])
def test_unknown_or_misspelt_settings_are_refused_with_a_suggestion(tmp_path, text, match):
    """A misspelt table or key used to leave the default (certificate 0.99) silently in force."""
    f = tmp_path / "typo.toml"
    f.write_text(text)
    with pytest.raises(GonioError, match=match) as e:
        load_settings(f)
    assert "\n" not in str(e.value)


def test_every_default_key_is_declared_in_the_schema():
    from gonio.bench.settings import SCHEMA

    for section, table in default_settings().items():
        assert set(table) <= set(SCHEMA[section]), section


def test_effective_settings_say_where_each_value_came_from(tmp_path):
    from gonio.bench.settings import effective_settings

    f = tmp_path / "lab.toml"
    f.write_text("[reference]\nreflectance = 0.97\ncertificate = \"NPL-123\"\n[session]\noperator = \"A. B.\"\n")
    s, source = effective_settings(f, {"session": {"operator": "C. D.", "sample_id": "S-7", "sample_description": None}})
    assert s["reference"]["reflectance"] == 0.97 and source["reference.reflectance"] == f"file {f}"
    assert source["reference.rel_std"] == "default" and s["session"] == {"operator": "C. D.", "sample_id": "S-7"}
    assert source["session.operator"] == "option" and "session.sample_description" not in source


def test_settings_show_cli(tmp_path, capsys):
    from gonio.cli.main import main

    f = tmp_path / "lab.toml"
    f.write_text("[reference]\nreflectance = 0.97\n")
    assert main(["settings", "show", "--settings", str(f), "--sample-id", "S-7"]) == 0
    out = capsys.readouterr().out.splitlines()
    # each value with its unit (gonio/cli/listing.py; "1": a dimensionless number) and its source
    assert f"reflectance = 0.97  # 1; file {f}" in out and "rel_std = 0.005  # 1; default" in out
    assert "settle_s = 0.2  # s; default" in out and "yaw = [1, 1, -95.0, 95.0]  # device, axis, deg, deg; default" in out
    assert 'sample_id = "S-7"  # option' in out                         # text: no unit
    f.write_text("[refrence]\nreflectance = 0.5\n")
    assert main(["settings", "show", "--settings", str(f)]) == 2
    err = capsys.readouterr().err
    assert "did you mean [reference]?" in err and len(err.strip().splitlines()) == 1


def test_capture_dry_run_needs_no_out(capsys):
    """The README's `gonio capture --sim --plan standard --dry-run` (it said: capture needs --out DIR)."""
    from gonio.cli.main import main

    assert main(["capture", "--sim", "--plan", "quick", "--dry-run"]) == 0
    assert "points; estimated duration" in capsys.readouterr().out


def test_tables_other_modules_check_pass_through(tmp_path):
    """[errors] (the simulator's error model) and the calibration tables are checked by their own
    modules; a misspelling of them is still caught here."""
    f = tmp_path / "e.toml"
    f.write_text('[errors]\npreset = "typical"\n[stray]\nfloor = 0.001\n')
    assert load_settings(f)["errors"] == {"preset": "typical"}
    f.write_text('[erors]\npreset = "typical"\n')
    with pytest.raises(GonioError, match=r"did you mean \[errors\]\?"):
        load_settings(f)


def test_capture_records_the_session_options_in_its_settings(tmp_path, monkeypatch, capsys):
    """--sample-id/--sample-description/--operator (over a [session] table) reach the capture's
    settings, which session.toml records, on the simulated and the real instrument alike."""
    import gonio.cli.capture as runner
    from gonio.cli.main import main

    seen = {}
    monkeypatch.setattr(runner, "capture_cli", lambda out, **kw: seen.update(kw) or 0)
    f = tmp_path / "lab.toml"
    f.write_text('[session]\noperator = "B. Other"\nsample_description = "PTFE tile"\n')
    argv = ["capture", "--port", "/dev/ttyUSB0", "--meter-port", "/dev/ttyUSB1", "--camera", "gphoto2",
            "--out", str(tmp_path / "s"), "--settings", str(f), "--sample-id", "S-0042", "--operator", "A. Tester"]
    assert main(argv) == 0
    assert seen["settings"]["session"] == {"operator": "A. Tester", "sample_description": "PTFE tile",
                                           "sample_id": "S-0042"}
    assert main(["capture", "--resume", str(tmp_path / "s"), "--operator", "X"]) == 2
    assert "is recorded when a session starts" in capsys.readouterr().err
    f.write_text('[sesion]\noperator = "B. Other"\n')
    assert main(argv) == 2 and "did you mean [session]?" in capsys.readouterr().err
    assert not (tmp_path / "s").exists()


def test_settings_show_expands_an_errors_preset(tmp_path):
    """`[errors] preset = "typical"` with one term overridden: each term's value says whether the
    preset or the file set it (the preset's values are gonio/sim/physics/errors.py's PRESETS["typical"])."""
    import gonio.sim
    from gonio.bench.settings import show_settings

    f = tmp_path / "e.toml"
    f.write_text('[errors]\npreset = "typical"\n[errors.stray]\nfloor = 0.0\n')
    lines = show_settings(f)
    typical = gonio.sim.error_model("typical").to_dict()
    assert f"repeat_deg = {typical['stages']['repeat_deg']}  # preset typical" in lines
    assert f"floor = 0.0  # file {f}" in lines
    f.write_text('[errors]\npreset = "typo"\n')
    with pytest.raises(GonioError, match="preset 'typo' is unknown"):
        show_settings(f)
