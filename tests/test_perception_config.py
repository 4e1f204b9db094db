"""Configuration files: the bundled ones load, mistakes are refused naming the field."""

import re

import pytest

from perception.config import CONFIG_DIR, Config, ConfigError, config_from_dict, config_to_toml, load_config
from perception.model import build_model, count_parameters


@pytest.mark.parametrize("name", sorted(p.stem for p in CONFIG_DIR.glob("*.toml")))
def test_bundled_configs_load_and_round_trip(name, tmp_path):
    config = load_config(CONFIG_DIR / f"{name}.toml")
    assert load_config(name) == config
    assert config_from_dict(config.to_dict()) == config
    written = tmp_path / "written.toml"
    written.write_text(config_to_toml(config, header="what ran\nand how"))
    assert written.read_text().startswith("# what ran\n# and how\n\n[model]\n")
    assert load_config(written) == config


def test_gpu_configs_keep_the_compact_network():
    """The GPU-trained weights are bundled in place of the CPU-trained ones, and fine-tuned: the same network."""
    compact = load_config("compact")
    for name in ("compact_gpu", "compact_gpu_pose", "compact_cpu_pose", "compact_cpu_both"):
        assert load_config(name).model == compact.model and load_config(name).loss == compact.loss
    assert load_config("compact_gpu_pose").train.stages == load_config("compact_cpu_pose").train.stages == ("pose",)
    assert load_config("compact_cpu_both").train.stages == ("segmentation", "pose")


def test_paper_sizes():
    config = load_config("paper")
    assert (config.model.image_size, config.model.point_feature, config.model.part_feature,
            config.model.hidden) == (224, 512, 256, 512)
    assert (config.loss.translation, config.loss.rotation_chamfer, config.loss.rotation_l2,
            config.loss.shape_chamfer) == (1.0, 20.0, 1.0, 1.0)
    assert config.model.resnet_width == 1.0 and config.model.resnet_blocks == (2, 2, 2, 2)


def test_compact_weights_fit_the_bundle_budget():
    model = build_model(load_config("compact").model, "ours")
    assert count_parameters(model) * 4 < 15 * 2**20  # float32 weights under 15 MB


def test_defaults():
    assert Config().model.max_parts == 20 and Config().train.freeze_segmentation


@pytest.mark.parametrize("text, message", [
    ("[model]\nimage_sise = 224\n", "unknown field model.image_sise"),
    ("[model]\nimage_size = 100\n", "model.image_size must be a multiple of 32"),
    ("[model]\nimage_size = '224'\n", "model.image_size must be an integer"),
    ("[loss]\npoints = 5000\n", "loss.points must be in 1..1000"),
    ("[loss]\ncrossing = -0.5\n", "loss.crossing must be >= 0"),
    ("[train.pose]\nlr = -1.0\n", "train.pose.lr must be > 0"),
    ("[train.segmentation]\nbatch_size = 1\n", "train.segmentation.batch_size must be >= 2"),
    ("[train]\nfreeze_segmentation = 1\n", "train.freeze_segmentation must be true or false"),
    ("[modle]\n", "unknown field modle"),
    ("[train]\nstages = ['pose', 'pose']\n", "train.stages must name segmentation and/or pose once each"),
    ("[train]\nstages = ['masks']\n", "train.stages must name segmentation and/or pose once each"),
    ("[train]\nprecision = 'float16'\n", "train.precision must be one of ['float32', 'bfloat16'], got 'float16'"),
    ("[model\n", "line 1"),
])
def test_mistakes_name_the_field(tmp_path, text, message):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=re.escape(message)) as info:
        load_config(path)
    assert str(path) in str(info.value)


def test_missing_file():
    with pytest.raises(ConfigError, match="not found"):
        load_config("no_such_config")


def test_base_merges_field_by_field(tmp_path):
    """A file that starts from another replaces only what it names; tables merge, lists replace whole."""
    (tmp_path / "parent.toml").write_text('base = "compact"\n[train.pose]\nlr = 5e-4\nbatch_size = 16\n')
    (tmp_path / "child.toml").write_text('base = "parent.toml"\n[train]\nstages = ["pose"]\n[train.pose]\nlr = 1e-4\n')
    compact, child = load_config("compact"), load_config(tmp_path / "child.toml")
    assert child.train.pose.lr == 1e-4 and child.train.pose.batch_size == 16
    assert child.train.stages == ("pose",)
    assert child.train.pose.warmup_steps == compact.train.pose.warmup_steps
    assert child.model == compact.model and child.train.segmentation == compact.train.segmentation
    # a run's record is the resolved configuration: it reads back the same without its base files
    written = tmp_path / "resolved" / "config.toml"
    written.parent.mkdir()
    written.write_text(config_to_toml(child))
    assert "base" not in written.read_text() and load_config(written) == child


def test_bundled_fine_tuning_configs_start_from_their_base():
    assert load_config("compact_cpu_both").train.pose == load_config("compact_cpu_pose").train.pose
    assert load_config("compact_cpu_both").train.segmentation.lr == 1e-3
    assert load_config("compact_gpu_pose").train.segmentation == load_config("compact_gpu").train.segmentation


@pytest.mark.parametrize("files, message", [
    ({"bad.toml": 'base = "bad.toml"\n'}, "makes a cycle"),
    ({"bad.toml": 'base = "other.toml"\n', "other.toml": 'base = "bad.toml"\n'}, "makes a cycle"),
    ({"bad.toml": 'base = "missing.toml"\n'}, "(the base of"),
    ({"bad.toml": "base = 3\n"}, "base must be a config name or path, got 3"),
    ({"bad.toml": 'base = "compact"\n[model]\nimage_size = 100\n'}, "model.image_size must be a multiple of 32"),
])
def test_bad_base_is_refused_naming_the_file(tmp_path, files, message):
    for name, text in files.items():
        (tmp_path / name).write_text(text)
    with pytest.raises(ConfigError, match=re.escape(message)) as info:
        load_config(tmp_path / "bad.toml")
    assert "bad.toml" in str(info.value)
