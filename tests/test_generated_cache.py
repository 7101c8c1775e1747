"""The cache of generated scenes: a scene copied from it is the scene ``generate`` writes, byte for
byte; it is ray-cast once per key; the key follows the settings, the generator's source and the
libraries behind the bytes; without a cache nothing changes."""

import hashlib
from pathlib import Path

import pytest

import pipeline.data.fingerprint as fp
import pipeline.data.generated_cache as gc
from pipeline.data.fingerprint import scene_fingerprint
from pipeline.data import synthetic
from pipeline.data.synthetic import GeneratedScene, generate

SMALL = GeneratedScene(seed=1, size=16, n_train=3, n_test=2)


def _files(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture
def counted(monkeypatch):
    """generate() as the cache calls it, counting the scenes it ray-casts."""
    calls = []

    def counting(out, **kwargs):
        calls.append(kwargs)
        return generate(out, **kwargs)
    monkeypatch.setattr(gc, "generate", counting)
    return calls


def test_a_scene_from_the_cache_is_the_generated_scene_byte_for_byte_and_cast_once(tmp_path, counted):
    fresh = generate(tmp_path / "fresh", seed=1, size=16, n_train=3, n_test=2)
    first = gc.place_generated(tmp_path / "a" / "scene", SMALL, tmp_path / "cache")
    second = gc.place_generated(tmp_path / "b" / "scene", SMALL, tmp_path / "cache")
    assert _files(first) == _files(fresh) == _files(second)
    assert scene_fingerprint(second).short == scene_fingerprint(fresh).short
    assert len(counted) == 1
    assert not [p for p in (tmp_path / "b").iterdir() if p.name != "scene"]  # no partial copy left


def test_other_settings_are_another_entry(tmp_path, counted):
    small = gc.place_generated(tmp_path / "a", SMALL, tmp_path / "cache")
    other = GeneratedScene(seed=1, size=8, n_train=3, n_test=2)
    bigger = gc.place_generated(tmp_path / "b", other, tmp_path / "cache")
    assert len(counted) == 2 and _files(small) != _files(bigger)
    assert gc.cache_key(SMALL) != gc.cache_key(other)
    assert gc.cache_key(SMALL) != gc.cache_key(GeneratedScene(seed=2, size=16, n_train=3, n_test=2))


def test_the_key_follows_the_generators_source_and_the_libraries(tmp_path, monkeypatch):
    before = gc.cache_key(SMALL)
    assert fp.generator_source() == Path(synthetic.__file__)  # the file read is the generator's
    edited = tmp_path / "synthetic.py"
    edited.write_bytes(fp.generator_source().read_bytes() + b"\n# one more line\n")
    monkeypatch.setattr(fp, "generator_source", lambda: edited)
    assert gc.cache_key(SMALL) != before
    monkeypatch.undo()
    assert gc.cache_key(SMALL) == before
    real_version = fp.metadata.version
    monkeypatch.setattr(fp.metadata, "version", lambda name: "0.0" if name == "Pillow" else real_version(name))
    assert gc.cache_key(SMALL) != before


def test_without_a_cache_the_scene_is_generated_in_place(tmp_path, counted, monkeypatch):
    monkeypatch.delenv(gc.CACHE_ENV, raising=False)
    assert gc.cache_from_environment() is None
    monkeypatch.setenv(gc.CACHE_ENV, "  ")
    assert gc.cache_from_environment() is None
    scene = gc.place_generated(tmp_path / "scene", SMALL, None)
    assert (scene / "transforms_test.json").is_file() and len(counted) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene"]
    monkeypatch.setenv(gc.CACHE_ENV, str(tmp_path / "kept"))
    assert gc.cache_from_environment() == tmp_path / "kept"


def test_a_scene_already_at_the_target_is_replaced_by_the_cached_one_only_when_it_differs(tmp_path, counted):
    target = gc.place_generated(tmp_path / "scene", SMALL, tmp_path / "cache")
    (target / "scene.json").write_text("{}")  # another scene at the target
    gc.place_generated(tmp_path / "scene", SMALL, tmp_path / "cache")
    assert _files(target) == _files(tmp_path / "cache" / gc.cache_key(SMALL))
