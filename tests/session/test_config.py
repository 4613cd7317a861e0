"""Session config: TOML + command-line overrides, validated; errors name the file and the field."""

from __future__ import annotations

import pytest

from dpmhw.session.config import LiveSettings, SessionConfigError, load_session_config, parse_overrides


def write(tmp_path, text: str):
    p = tmp_path / "session.toml"
    p.write_text(text)
    return p


def test_defaults_are_valid_and_live_settings_follow_the_file():
    cfg = load_session_config()
    assert cfg.api.host == "127.0.0.1"
    live = cfg.live_settings()
    assert live == LiveSettings(alpha=cfg.reuse.alpha, reuse_mode=cfg.reuse.mode, spp=cfg.render.spp,
                                split_screen=False, prediction=True)


def test_file_and_overrides_merge(tmp_path):
    p = write(tmp_path, '[render]\nspp = 4\nwidth = 128\nheight = 96\n[[bindings]]\nrigid_body = 3\nobject = "bunny"\n')
    cfg = load_session_config(p, ["render.spp=2", "reuse.mode=off", 'api.token="s3cret"', "safety.resume=manual"])
    assert (cfg.render.spp, cfg.render.width, cfg.reuse.mode, cfg.api.token) == (2, 128, "off", "s3cret")
    assert cfg.safety.resume == "manual"
    assert cfg.bindings[0].rigid_body == 3 and cfg.bindings[0].object == "bunny"
    assert cfg.resolve("scene.toml") == tmp_path.resolve() / "scene.toml"


@pytest.mark.parametrize(
    "text, overrides, field",
    [
        ("[reuse]\nalpha = 0.0\n", [], "reuse.alpha"),
        ("[reuse]\nalpha = 1.5\n", [], "reuse.alpha"),
        ("[render]\nspp = 0\n", [], "render.spp"),
        ("[render]\nsppp = 2\n", [], "render.sppp"),
        ("", ["reuse.mode=magic"], "reuse.mode"),
        ("", ["api.port=70000"], "api.port"),
        ("", ["api.port=9000", "api.operator_port=9000"], "api.operator_port"),
        ("", ["safety.stale_after_ms=-1"], "safety.stale_after_ms"),
        ('[[bindings]]\nrigid_body = -2\nobject = "bunny"\n', [], "bindings[0].rigid_body"),
        ("[render]\nwidth = 640\n", [], "render"),
        ("", ["render.shading_scale=0.3"], "render.shading_scale"),
    ],
)
def test_bad_values_name_the_file_and_the_field(tmp_path, text, overrides, field):
    p = write(tmp_path, text)
    with pytest.raises(SessionConfigError) as info:
        load_session_config(p, overrides)
    msg = str(info.value)
    assert str(p) in msg and f": {field}" in msg, msg


def test_missing_file_bad_toml_and_bad_override(tmp_path):
    with pytest.raises(SessionConfigError, match="no such session config file"):
        load_session_config(tmp_path / "nope.toml")
    with pytest.raises(SessionConfigError, match="not valid TOML"):
        load_session_config(write(tmp_path, "[render\n"))
    with pytest.raises(SessionConfigError, match="section.field=value"):
        parse_overrides(["spp"])


def test_override_values_parse_as_toml():
    assert parse_overrides(["a.b=2", "a.c=true", "a.d=hello", 'a.e="x y"', "a.f=[1, 2]"]) == {
        "a": {"b": 2, "c": True, "d": "hello", "e": "x y", "f": [1, 2]}
    }


def test_env_token_wins(monkeypatch):
    cfg = load_session_config(overrides=["api.token=fromfile"])
    monkeypatch.setenv("DPMHW_API_TOKEN", "fromenv")
    assert cfg.api_token() == "fromenv"


def test_live_settings_reject_out_of_range():
    with pytest.raises(ValueError):
        LiveSettings(alpha=0)
    with pytest.raises(ValueError):
        LiveSettings(spp=0)
    with pytest.raises(ValueError):
        LiveSettings(colour="red")


def _float_fields():
    """(section.field, is a tuple) of every float in the config."""
    from dpmhw.session.config import SessionConfig

    for section, info in SessionConfig.model_fields.items():
        model = info.annotation
        for name, field in getattr(model, "model_fields", {}).items():
            if field.annotation is float or field.annotation == tuple[float, float, float]:
                yield f"{section}.{name}", field.annotation is not float


@pytest.mark.parametrize("path, is_tuple", list(_float_fields()))
@pytest.mark.parametrize("value", ["nan", "inf", "-inf", "1e-320", "-5e-324"])
def test_every_float_refuses_non_finite_and_subnormal_values_naming_the_field(path, is_tuple, value):
    shown = f"[{value}, 0.0, 0.0]" if is_tuple else value
    with pytest.raises(SessionConfigError) as info:
        load_session_config(None, [f"{path}={shown}"])
    lines = str(info.value).splitlines()
    assert len(lines) >= 1 and all(line.startswith(f"command line: {path}") for line in lines), lines


def test_the_float_table_is_not_empty():
    paths = [p for p, _ in _float_fields()]
    assert {"reuse.alpha", "render.target_fps", "tracker.workspace_min", "safety.watchdog_s"} <= set(paths)
