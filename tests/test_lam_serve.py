"""Serving LAM avatars: a `.zip` dropped into the avatars directory (imported once, cached by content), the
`avatar_zip` setting, `welcome.avatar.expression`, the ARKit path of the pipeline (no EPM), and live sessions
in which jawOpen moves only the lower face's Gaussians and eyeBlinkLeft only the left lid's (on a small zip
written here, and on the real statue in ../shared/data when present)."""

from __future__ import annotations

from pathlib import Path

import lam_fixtures as L
import numpy as np
import pytest
from ofera.client import ServerError, connect
from ofera.mapping.layouts import ARKIT52_NAMES
from ofera.streaming import Settings, offline_pipeline
from ofera.streaming.registry import AvatarRegistry
from ofera.streaming.server import ServerThread
from test_server_support import SMALL, main_server, private_cache, run

STATUE = Path(__file__).resolve().parents[2] / "shared" / "data" / "lam_statue.zip"


@pytest.fixture(scope="module")
def env():
    """An avatars directory (face.zip, broken.zip, statue.zip -> the real one if present), a private cache,
    and a server on it."""
    with private_cache("ofera-lam-") as root:
        avatars = root / "avatars"
        L.make_zip(avatars / "face.zip", junk=True, extra_json=True)
        (avatars / "broken.zip").write_bytes(b"PK\x03\x04 not really a zip")
        if STATUE.is_file():
            (avatars / "statue.zip").symlink_to(STATUE)
        settings = Settings(host="127.0.0.1", port=0, avatars=avatars, default_avatar="face", log_level="warning",
                            compute_threads=2, hello_timeout=5.0)
        server = ServerThread(settings).start()
        try:
            yield settings, server, root
        finally:
            server.stop()


def arkit52(**named: float) -> np.ndarray:
    w = np.zeros(52, np.float32)
    for k, v in named.items():
        w[ARKIT52_NAMES.index(k)] = v
    return w


async def frames(url: str, avatar: str, shapes: list[np.ndarray], **hello):
    """Neutral positions (N, 3) and the positions of one frame per weight vector (arkit52), f32 dense."""
    async with await connect(url, avatar=avatar, **hello) as c:
        out = []
        for w in shapes:
            seq = await c.send_bs(w)
            f = await c.recv_frame(timeout=60)
            while f.seq != seq:
                f = await c.recv_frame(timeout=60)
            out.append((f.position.copy(), dict(f.timing)))
        return c.welcome, c.avatar.position.copy(), out


def moved(a: np.ndarray, b: np.ndarray, tol: float) -> np.ndarray:
    return np.linalg.norm(a - b, axis=1) > tol


def test_welcome_says_what_drives_the_avatar(env) -> None:
    _, server, _ = env
    welcome, _, _ = run(frames(server.url, "face", []))
    assert welcome.avatar.expression == "arkit51" and welcome.avatar.sh_degree == 0
    welcome, _, _ = run(frames(main_server().url, SMALL, []))
    assert welcome.avatar.expression == "flame68"


def test_live_jaw_open_and_blink_move_only_their_regions(env) -> None:
    _, server, _ = env
    welcome, neutral, out = run(frames(server.url, "face", [arkit52(jawOpen=1), arkit52(eyeBlinkLeft=1),
                                                            arkit52()]))
    (jaw, timing), (blink, _), (zero, _) = out
    v, _, deltas = L.patch()
    centre = (v.min(0) + v.max(0)) / 2
    lower = v[:, 1] < L.LOWER_FACE_Y
    left_lid = np.linalg.norm(v[:, :2] - L.EYE_LEFT, axis=1) < 0.016
    np.testing.assert_array_equal(moved(jaw, neutral, 1e-6), lower)
    np.testing.assert_array_equal(moved(blink, neutral, 1e-6), left_lid)
    np.testing.assert_allclose(jaw - neutral, deltas["jawOpen"], atol=1e-6)
    assert np.all(neutral[left_lid, 0] > 0), "the left lid is on the subject's left (+x)"
    np.testing.assert_array_equal(zero, neutral)
    assert np.abs(neutral - (v - centre)).max() < 0.02  # the Gaussians sit on the centred patch
    assert {"layout", "bda", "epm", "head", "deform"} <= set(timing), timing


@pytest.mark.skipif(not STATUE.is_file(), reason=f"{STATUE} is absent (real LAM data: ../shared/data)")
def test_live_statue_jaw_open_and_blink(env) -> None:
    settings, server, _ = env
    welcome, neutral, out = run(frames(server.url, "statue", [arkit52(jawOpen=1), arkit52(eyeBlinkLeft=1)],
                                       encoding="f32"))
    assert welcome.avatar.count == 20018 and welcome.avatar.expression == "arkit51"
    (jaw, _), (blink, _) = out
    head = AvatarRegistry(settings).get("statue").avatar.head
    v = head.v_template  # each Gaussian binds to the vertex of its own index
    nose_y = v[v[:, 2].argmax(), 1]
    jaw_moved, blink_moved = moved(jaw, neutral, 2e-3), moved(blink, neutral, 1e-3)
    assert jaw_moved.sum() > 1000 and blink_moved.sum() > 300
    assert v[jaw_moved, 1].max() < nose_y, "jawOpen moved Gaussians above the nose"
    assert np.all(v[blink_moved, 0] > 0) and np.all(v[blink_moved, 1] > nose_y), "eyeBlinkLeft left the left lid"
    assert not moved(blink, neutral, 1e-3)[v[:, 0] < 0].any()
    assert (jaw - neutral)[jaw_moved, 1].mean() < -0.005  # the chin goes down


def test_frames_match_the_offline_pipeline_in_every_layout(env) -> None:
    settings, server, _ = env
    rng = np.random.default_rng(2)
    w = rng.uniform(0, 1, 52).astype(np.float32)
    _, _, [(pos, _)] = run(frames(server.url, "face", [w]))
    state, timings = offline_pipeline("face", "arkit52", w, settings=settings)
    assert pos.tobytes() == state.position.tobytes()
    assert set(timings) == {"layout", "bda", "epm", "head", "deform"}
    reference = offline_pipeline("face", "arkit52", w, settings=settings.model_copy(update={"fast": False}))[0]
    np.testing.assert_allclose(reference.position, state.position, atol=1e-7)
    for layout, n in (("ovr63", 63), ("livelink61", 61), ("mediapipe52", 52)):
        st, _ = offline_pipeline("face", layout, rng.uniform(0, 1, n).astype(np.float32), settings=settings)
        assert np.all(np.isfinite(st.position))


def test_zip_is_imported_once_and_cached(env, monkeypatch) -> None:
    settings, _, root = env
    AvatarRegistry(settings).get("face")
    cached = list((root / "cache" / "lam").glob("face-*.npz"))
    assert len(cached) == 1

    def no_import(*a, **k):
        raise AssertionError("imported again instead of reading the cache")

    import ofera.avatar.lam as lam

    monkeypatch.setattr(lam, "import_lam", no_import)
    assets = AvatarRegistry(settings).get("face")  # a new registry (another process): from the cache
    assert assets.expression == "arkit51" and assets.mapper is None


def test_a_bad_zip_is_refused_and_the_server_goes_on(env) -> None:
    _, server, _ = env
    with pytest.raises(ServerError) as err:
        run(frames(server.url, "broken", []))
    assert err.value.code == "internal" and "not a readable zip" in err.value.message
    welcome, _, _ = run(frames(server.url, "face", [arkit52(jawOpen=0.5)]))
    assert welcome.avatar.id == "face"


def test_avatar_zip_setting_is_the_default_unless_told_otherwise(tmp_path) -> None:
    z = L.make_zip(tmp_path / "anna.zip")
    reg = AvatarRegistry(Settings(avatar_zip=z))
    assert reg.resolve("default") == "anna" and reg.sources["anna"].path == z
    reg = AvatarRegistry(Settings(avatar_zip=z, default_avatar="default"))
    assert reg.resolve("default") == "default" and reg.resolve("anna") == "anna"
    with pytest.raises(FileNotFoundError, match="does not exist"):
        AvatarRegistry(Settings(avatar_zip=tmp_path / "missing.zip"))


def test_default_id_rule_is_one_for_the_registry_and_the_cli(tmp_path, monkeypatch) -> None:
    import ofera.streaming.server as server_module
    from ofera.cli.main import app
    from typer.testing import CliRunner

    z = L.make_zip(tmp_path / "anna.zip")
    for settings, expect in ((Settings(avatar_zip=z), "anna"), (Settings(avatar_zip=z, default_avatar="default"),
                                                                 "default"), (Settings(), "default")):
        assert AvatarRegistry.default_id_for(settings) == expect == AvatarRegistry(settings).default_id
    served = []
    monkeypatch.setattr(server_module, "serve", lambda settings: served.append(settings))
    for args, expect in ((["--avatar-zip", str(z)], "anna"),
                         (["--avatar-zip", str(z), "--default-avatar", "default"], "default")):
        res = CliRunner().invoke(app, ["serve", "--port", "0", *args])
        assert res.exit_code == 0, res.output
        assert f"warming up avatar {expect!r}" in res.output, res.output
        assert AvatarRegistry.default_id_for(served[-1]) == expect


def test_avatar_listing_says_arkit_avatars_load_no_epm(tmp_path, monkeypatch) -> None:
    from ofera.avatar import save_avatar
    from ofera.avatar.lam import import_lam

    monkeypatch.setenv("OFERA_CACHE", str(tmp_path / "cache"))
    avatars = tmp_path / "avatars"
    avatars.mkdir()
    L.make_zip(avatars / "face.zip")
    (avatars / "face.onnx").write_bytes(b"not loaded: an ARKit avatar takes no EPM")
    save_avatar(import_lam(L.make_zip(tmp_path / "lam.zip")), avatars / "imported.npz")
    reg = AvatarRegistry(Settings(avatars=avatars, avatar_zip=L.make_zip(tmp_path / "anna.zip")))
    listing = {d["id"]: d for d in reg.describe()}
    assert listing["anna"]["epm"] == listing["face"]["epm"] == "none", listing
    assert listing["default"]["epm"] == "default"
    reg.get("imported")  # an .npz says what drives it once loaded
    reg.get("face")
    listing = {d["id"]: d for d in reg.describe()}
    assert listing["imported"]["epm"] == listing["face"]["epm"] == "none", listing
    assert listing["imported"]["expression"] == "arkit51"
