"""A config's ``dataset`` section as a dataclass (``DatasetSectionCfg``): loaded by the typed
loader with the other sections, checked once with messages that name the key and the file,
and built from the plain mappings evaluation code passes."""

import dataclasses
from pathlib import Path

import pytest

from tests.data.fakes import fake_scene, write_plain_dataset
from usplat_dr.config import ConfigError, load_config, load_typed
from usplat_dr.data import ViewSamplerAllCfg, ViewSamplerBoundedCfg, ViewSamplerEvaluationCfg
from usplat_dr.data.dataset import (
    DATASET_PRESETS,
    PRESET_CONFIGS,
    DatasetSectionCfg,
    dataset_cfg,
    dataset_from_section,
)


def section_from_yaml(tmp_path: Path, text: str) -> DatasetSectionCfg:
    path = tmp_path / "mine.yaml"
    path.write_text(text)
    cfg = load_config([path])
    return load_typed(DatasetSectionCfg, cfg.get("dataset"), "dataset", cfg.origins)


def test_a_section_loads_in_its_normal_form(tmp_path):
    section = section_from_yaml(tmp_path, (
        "dataset:\n  name: dtu\n  roots: data/dtu\n  image_shape: [32, 48]\n"
        "  view_sampler: {name: all}\n  overrides: {near: 1, augment: false}\n"))
    assert section.roots == ("data/dtu",)  # one folder: a tuple of one
    assert section.image_shape == (32, 48) and section.view_sampler == ViewSamplerAllCfg()
    assert section.overrides == {"near": 1.0, "augment": False}  # typed by DatasetCfg
    assert isinstance(section.overrides["near"], float)
    # image_shape wins over the same key of overrides, as DatasetCfg's settings
    assert dataclasses.replace(section, overrides={"image_shape": (8, 8)}).dataset_overrides() \
        == {"image_shape": (32, 48)}
    assert section_from_yaml(tmp_path, "seed: 1\n") == DatasetSectionCfg()  # the defaults
    bounded = section_from_yaml(tmp_path, "dataset:\n  view_sampler: {num_target_views: 2}\n")
    assert bounded.view_sampler == ViewSamplerBoundedCfg(num_target_views=2)


def test_the_sampler_of_a_stage():
    section = DatasetSectionCfg.from_dict({"roots": ["d"], "evaluation_index": "index.json"})
    assert isinstance(section.sampler("train"), ViewSamplerBoundedCfg)  # training's own
    assert section.sampler("test") == section.sampler("val") == ViewSamplerEvaluationCfg(
        "index.json")
    assert DatasetSectionCfg.from_dict({"roots": ["d"]}).sampler("test").name == "bounded"


def test_a_presets_sampler_is_its_packaged_configs(tmp_path):
    # The Python presets (dataset_cfg, the plain mappings of evaluation code) and the YAML
    # configs train with the same view sampler: the packaged dataset config's.
    assert set(PRESET_CONFIGS) == set(DATASET_PRESETS)
    write_plain_dataset(tmp_path, "train", [[fake_scene("s0", 3, shape=(8, 8), fmt="png")]])
    for name, config in PRESET_CONFIGS.items():
        cfg = load_config(config)
        from_yaml = load_typed(DatasetSectionCfg, cfg["dataset"], "dataset", cfg.origins)
        assert from_yaml.name == name
        assert dataset_cfg(name, "d").view_sampler == from_yaml.view_sampler, name
        plain = dataset_from_section({"name": name, "roots": [str(tmp_path)]}, "train")
        assert plain.cfg.view_sampler == from_yaml.view_sampler, name
    # the synthetic sets' gaps (`usplat synth` writes 24 frames a scene), not RE10K's
    # 25-45 then 45-192
    synth = load_typed(DatasetSectionCfg, load_config("synthetic_tiny.yaml")["dataset"])
    assert synth.view_sampler == dataset_cfg("synth", "d").view_sampler
    gaps = dataset_cfg("synth", "d").view_sampler
    assert (gaps.initial_min_distance_between_context_views,
            gaps.initial_max_distance_between_context_views,
            gaps.min_distance_between_context_views,
            gaps.max_distance_between_context_views, gaps.warm_up_steps) == (4, 8, 4, 8, 1)
    assert dataset_cfg("re10k", "d").view_sampler == ViewSamplerBoundedCfg()  # MVSplat's
    # a sampler given explicitly wins
    assert dataset_cfg("synth", "d", view_sampler=ViewSamplerAllCfg()).view_sampler \
        == ViewSamplerAllCfg()


@pytest.mark.parametrize("text, message", [
    ("dataset: [1]\n", r"dataset must be a mapping"),
    ("dataset:\n  nmae: re10k\n", r"unknown key 'dataset\.nmae'"),
    ("dataset:\n  name: imagenet\n", r"dataset\.name='imagenet' must be one of \['acid'"),
    ("dataset:\n  roots: 5\n", r"dataset\.roots=5: expected str or tuple"),
    ("dataset:\n  image_shape: [32]\n", r"dataset\.image_shape=\[32\]: expected"),
    ("dataset:\n  image_shape: [0, 32]\n", r"dataset\.image_shape=\[0, 32\] must be two sizes"),
    ("dataset:\n  image_shape: [1000000, 1000000]\n", r"at most .* pixels"),
    ("dataset:\n  overrides: {image_shape: [0, 1]}\n", r"dataset\.overrides\.image_shape="),
    ("dataset:\n  overrides: {nearr: 1}\n", r"unknown key\(s\) \['nearr'\] in dataset\.overrides"),
    ("dataset:\n  overrides: {skip_bad_shape: maybe}\n",
     r"dataset\.overrides\.skip_bad_shape='maybe': expected bool"),
    ("dataset:\n  overrides: {near: 5, far: 1}\n", r"near=5\.0, far=1\.0 must be 0 < near < far"),
    ("dataset:\n  overrides: [1]\n", r"dataset\.overrides=\[1\]: expected dict"),
    ("dataset:\n  view_sampler: [1]\n", r"dataset\.view_sampler=\[1\] must be a mapping"),
    ("dataset:\n  view_sampler: {name: random}\n",
     r"dataset\.view_sampler\.name='random' must be one of \['all', 'bounded', 'evaluation'\]"),
    ("dataset:\n  view_sampler: {num_target_views: four}\n",
     r"dataset\.view_sampler\.num_target_views='four': expected int"),
    ("dataset:\n  view_sampler: {name: evaluation}\n",
     r"dataset\.view_sampler needs \['index_path'\]"),
])
def test_mistakes_name_the_key_and_the_file(tmp_path, text, message):
    with pytest.raises(ConfigError, match=message) as raised:
        section_from_yaml(tmp_path, text)
    assert "mine.yaml" in str(raised.value)


def test_plain_mappings_of_evaluation_code(tmp_path):
    write_plain_dataset(tmp_path, "test", [[fake_scene("s0", 10, shape=(32, 32), fmt="png")]])
    index = tmp_path / "index.json"
    index.write_text('{"s0": {"context": [0, 4], "target": [2]}}')
    # folders and files as Paths, as evaluation code has them
    plain = {"name": "re10k", "roots": [tmp_path], "image_shape": (16, 16),
             "evaluation_index": index, "overrides": {"skip_bad_shape": False}}
    ds = dataset_from_section(plain, "test")
    assert ds.cfg.roots == (str(tmp_path),) and ds.cfg.image_shape == (16, 16)
    assert ds.cfg.view_sampler == ViewSamplerEvaluationCfg(str(index))
    example, = list(ds)
    assert example["target"]["index"].tolist() == [2]
    # a loaded section builds the same dataset; its asdict (a checkpoint's config) loads back
    section = DatasetSectionCfg.from_dict(plain)
    assert dataset_from_section(section, "test").cfg == ds.cfg
    assert DatasetSectionCfg.from_dict(dataclasses.asdict(section)) == section
    with pytest.raises(ConfigError, match="dataset.roots must name at least one"):
        dataset_from_section({"name": "synth"}, "test")
    with pytest.raises(ConfigError, match=r"dataset\.name='imagenet'"):
        dataset_from_section({**plain, "name": "imagenet"}, "test")
