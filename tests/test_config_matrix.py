"""Every preset with every algorithm, logger and disturbance preset: the options of conf/experiment,
conf/algo, conf/logger and conf/disturbance, composed as drone-train composes them (the command
line's checks, Hydra, validation). The expected outcome of each combination is in :data:`MATRIX`, so
an option that starts or stops working fails here; a new option needs its rows.

Outcomes: ``trains``; ``note``: trains, and a note names the preset's keys the algorithm does not
take (dropped); ``preset``: refused, the preset is made for another algorithm, and the message names
``experiment=bounded algo=<x>`` as the way; ``bounded``: refused, the algorithm needs bounded thrust
(SAC's TanhNormal actor) and the preset's Normal head is named. A logger whose extra is not installed (``logger=mlflow`` without
``drone_torchrl[mlflow]``) refuses every combination that would train, naming the extra: the
expectation is computed from what is importable, so the plain ``.[test]`` install passes too.
"""

from __future__ import annotations

import itertools
import time

import pytest
from hydra import compose, initialize_config_dir

from drone_torchrl import loggers
from drone_torchrl.config import (
    ConfigError,
    _option_plugins,
    check_overrides,
    config_dir,
    group_options,
    preset_notes,
    schema_keys,
    validate,
)

GROUPS = ("experiment", "algo", "logger", "disturbance")
DISTURBANCES = ("none", "mild", "strong")
# experiment, algo: the outcome under disturbance=none, mild, strong (any logger whose extra is there)
MATRIX = """
bounded        a2c             trains   trains   trains
bounded        ppo             trains   trains   trains
bounded        reinforce       trains   trains   trains
bounded        reinforce_plus  trains   trains   trains
hover_optimal  a2c             preset   preset   preset
hover_optimal  ppo             trains   trains   trains
hover_optimal  reinforce       preset   preset   preset
hover_optimal  reinforce_plus  preset   preset   preset
paper          a2c             trains   trains   trains
paper          ppo             trains   trains   trains
paper          reinforce       trains   trains   trains
paper          reinforce_plus  trains   trains   trains
paper_code     a2c             note     note     note
paper_code     ppo             note     note     note
paper_code     reinforce       trains   trains   trains
paper_code     reinforce_plus  trains   trains   trains
randomised     a2c             preset   preset   preset
randomised     ppo             trains   trains   trains
randomised     reinforce       preset   preset   preset
randomised     reinforce_plus  preset   preset   preset
bounded        sac             trains   trains   trains
hover_optimal  sac             preset   preset   preset
paper          sac             bounded  bounded  bounded
paper_code     sac             bounded  bounded  bounded
randomised     sac             preset   preset   preset
"""
TRAINS = ("trains", "note")
# The minute the 240 combinations before algo=sac had, per combination.
SECONDS_PER_COMBINATION = 0.25
# What the one line of each refusal names ({algo}: the combination's algorithm option).
REFUSALS = {
    "preset": "experiment=bounded algo={algo}",
    "bounded": "model.distribution='normal' is not allowed; expected 'tanh_normal' with algo.name={algo}",
}
PAPER_CODE_NOTE = (
    "experiment=paper_code: algo.optimizer, algo.weight_decay, algo.log_prob_reduction do not apply to "
    "algo={algo}; dropped"
)


def _table() -> dict[tuple[str, str, str], str]:
    rows = {}
    for line in MATRIX.strip().splitlines():
        experiment, algo, *outcomes = line.split()
        for disturbance, outcome in zip(DISTURBANCES, outcomes, strict=True):
            rows[experiment, algo, disturbance] = outcome
    return rows


def _missing_extra(logger: str) -> str | None:
    """The extra ``logger=<logger>`` needs that is not installed, or None."""
    backend = loggers.get(_option_plugins("config", (("logger", logger),))["logger"])
    return None if backend.installed else backend.extra


def _expected(experiment: str, algo: str, logger: str, disturbance: str) -> str:
    outcome = _table()[experiment, algo, disturbance]
    if outcome in TRAINS and _missing_extra(logger) is not None:
        return "extra"
    return outcome


def _combinations() -> list[tuple[str, ...]]:
    return list(itertools.product(*(group_options(group) for group in GROUPS)))


def _compose(combination: tuple[str, ...], *extra: str) -> dict[str, str]:
    """check_overrides (the command line's checks), Hydra's composition and validation, as drone-train
    runs them; returns the groups' choices. Raises ConfigError."""
    overrides = [*(f"{g}={o}" for g, o in zip(GROUPS, combination, strict=True)), *extra]
    check_overrides(overrides)
    cfg = compose("config", overrides=overrides, return_hydra_config=True)
    validate(cfg)
    return dict(cfg.hydra.runtime.choices)


def test_the_table_covers_every_combination():
    table = {(experiment, algo, disturbance) for experiment, algo, _, disturbance in _combinations()}
    assert set(_table()) == table, "MATRIX needs a row for each experiment and algo option (and only those)"
    assert set(DISTURBANCES) == set(group_options("disturbance"))


@pytest.mark.slow  # 300 compositions, about 50 s on 2 cores: with the matrix's training below
def test_every_combination_is_composed_and_validated_as_the_table_says():
    """All of them (300 with 5 presets, 5 algorithms, 4 loggers, 3 disturbances), each in at most
    SECONDS_PER_COMBINATION on average."""
    start = time.perf_counter()
    got, counts = {}, {}
    with initialize_config_dir(config_dir(), version_base="1.3"):
        for combination in _combinations():
            experiment, algo, logger, disturbance = combination
            expected = _expected(*combination)
            try:
                choices = _compose(combination)
            except ConfigError as err:
                message = str(err)
                assert "\n" not in message, (combination, message)
                if expected == "extra":
                    assert f"drone_torchrl[{_missing_extra(logger)}]" in message, (combination, message)
                elif expected in REFUSALS:
                    assert REFUSALS[expected].format(algo=algo) in message, (combination, message)
                got[combination] = expected if expected not in TRAINS else f"refused: {message}"
            else:
                notes = preset_notes(choices)
                got[combination] = "note" if notes else "trains"
                if notes:
                    assert notes == [PAPER_CODE_NOTE.format(algo=algo)], (combination, notes)
            counts[got[combination]] = counts.get(got[combination], 0) + 1
    elapsed = time.perf_counter() - start
    print(f"{len(got)} combinations in {elapsed:.1f} s: {counts}")
    assert {c: o for c, o in got.items() if o != _expected(*c)} == {}
    assert elapsed <= SECONDS_PER_COMBINATION * len(got)


# A run as short as it gets: 2 episodes of 10 steps, no periodic evaluation, no video; on-policy
# batches of 2 drones x 10 steps (keys a plug-in does not have are left out).
SHORT = {
    "algo.episodes": 2,
    "env.max_steps": 10,
    "eval.every_episodes": 0,
    "eval.stop_return": "null",  # hover_optimal's stop and rollback need periodic evaluations
    "eval.rollback_drop": "null",
    "eval.episodes": 1,
    "eval.video": "false",
    "checkpoint.every_episodes": 1000,
    "progress": "false",
    "algo.episodes_per_update": 1,
    "algo.num_envs": 2,
    "algo.steps_per_batch": 10,
    "algo.minibatch_size": 20,
    "algo.epochs": 1,
}


@pytest.mark.slow  # about 120 runs
def test_every_allowed_combination_trains_two_short_episodes(tmp_path):
    from drone_torchrl.training.trainer import train

    start = time.perf_counter()
    trained = 0
    with initialize_config_dir(config_dir(), version_base="1.3"):
        for i, combination in enumerate(_combinations()):
            if _expected(*combination) not in TRAINS:
                continue
            plugins = _option_plugins("config", (("experiment", combination[0]), ("algo", combination[1])))
            keys = schema_keys("config", algo=plugins["algo"])
            overrides = [*(f"{g}={o}" for g, o in zip(GROUPS, combination, strict=True))]
            overrides += [f"{k}={v}" for k, v in SHORT.items() if k in keys]
            check_overrides(overrides)
            # One folder for all: the mlflow runs share one store beside them.
            final = train(compose("config", overrides=overrides), tmp_path / f"{i}-{'-'.join(combination)}")
            assert final is not None, combination
            trained += 1
    elapsed = time.perf_counter() - start
    print(f"{trained} combinations trained in {elapsed:.0f} s")
    assert elapsed <= 300
