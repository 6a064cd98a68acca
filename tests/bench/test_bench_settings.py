"""Instrument settings: defaults, overrides, one-line errors."""

import pytest

from gonio.bench._settings import default_settings, load_settings, merge_settings
from gonio.bench.errors import GonioError


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
