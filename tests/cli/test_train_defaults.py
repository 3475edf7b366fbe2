"""`aefabmap train`'s option defaults are TrainConfig's: one default per setting."""

from __future__ import annotations

import dataclasses

import pytest

from aefabmap.cli.main import build_parser
from aefabmap_trainer.train import TrainConfig


def test_every_train_option_defaults_to_the_config_default():
    args = vars(build_parser().parse_args(["train", "--images", "imgs", "--out", "b"]))
    shared = [f for f in dataclasses.fields(TrainConfig) if f.name in args and f.default is not dataclasses.MISSING]
    assert len(shared) >= 20  # words, seed, descriptors and every --ae-* option
    assert {f.name: args[f.name] for f in shared} == {f.name: f.default for f in shared}


def test_the_default_autoencoder_is_the_assign_objective_measured_best():
    c = TrainConfig(images=(), out="b", quantizer="ae")
    # docs/results.md, "The word-assignment objective": 6 views a track, reconstruction weight 1, 8 epochs.
    assert (c.ae_objective, c.ae_arch, c.ae_views, c.ae_light_views, c.ae_recon_weight, c.ae_epochs) == \
        ("assign", "light", 6, 0, 1.0, 8)


def test_the_word_usage_weight_and_temperature_default_to_assign_configs():
    """(The reconstruction weight differs on purpose: the objective alone has none, the default AE 1.)"""
    pytest.importorskip("torch")
    from aefabmap_trainer.assign_objective import AssignConfig

    c, a = TrainConfig(images=(), out="b", quantizer="ae"), AssignConfig()
    assert (c.ae_balance_weight, c.ae_temperature_end) == (a.balance_weight, a.temperature_end)


def test_the_descriptor_training_options_default_to_its_config():
    from aefabmap_trainer.learned_descriptor import DescriptorTraining

    args = vars(build_parser().parse_args(["train", "--images", "imgs", "--out", "b"]))
    d = DescriptorTraining()
    assert (args["descriptor_images"], args["descriptor_epochs"], args["descriptor_warp"]) == (d.images, d.epochs, d.warp)
