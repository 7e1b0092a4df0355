"""Configuration: validation with clear one-line messages, TOML overrides, and a stable hash."""

from __future__ import annotations

import copy
import math
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from mpi_lidar.config import (
    PAPER_FREQUENCIES_HZ,
    PAPER_SAMPLES,
    Config,
    PriorConfig,
    config_from_json,
    config_json,
    config_sha256,
    load_config,
    preset,
)
from mpi_lidar.errors import ConfigError

pytestmark = pytest.mark.unit

NYQUIST_HZ = 1 / (2 * 6e-9)  # 83.3 MHz


def write_toml(tmp_path: Path, text: str, name: str = "config.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def test_config__defaults_are_table_i(config):
    s = config.sensor
    assert config.frequencies_hz == PAPER_FREQUENCIES_HZ == (12.5e6, 18.75e6, 25e6, 31.25e6)
    assert (s.gamma_r_v2, s.demodulation_amplitude_v, s.tia_gain_v_per_a) == (0.1794, 0.4785, 50e3)
    assert (s.quantum_efficiency, s.avalanche_gain, s.excess_noise_factor) == (0.67, 50.0, 4.862)
    assert (s.transit_time_s, s.integration_time_s, s.wavelength_m) == (6e-9, 16e-6, 852e-9)
    assert config.prior.scheme == "reciprocal"
    assert config.simulator.fidelity == "moment" and config.simulator.round_photons
    assert not config.simulator.whole_cycles


def test_config__is_frozen(config):
    with pytest.raises(ValidationError, match="frozen"):
        config.simulator.noise_scale = 0.0  # type: ignore[misc]


def test_config_replace__changes_one_nested_field_only(config):
    quiet = config.replace(simulator={"noise_scale": 0.0})
    assert quiet.simulator.noise_scale == 0.0
    assert quiet.simulator.model_dump(exclude={"noise_scale"}) == config.simulator.model_dump(exclude={"noise_scale"})
    assert quiet.sensor == config.sensor and quiet.prior == config.prior


INVALID_REPLACEMENTS = [
    # (sections for Config().replace, expected fragment of the message)
    ({"prior": {"d_as_m": (-1.0, 2.0)}}, "d_as_m must be positive"),
    ({"prior": {"d_as_m": (0.0, 2.0)}}, "d_as_m must be positive"),
    ({"prior": {"d_ab_m": (-0.1, 0.1)}}, "d_ab_m must be non-negative"),
    ({"prior": {"d_as_m": (2.4, 1.4)}}, "low <= high"),
    ({"prior": {"d_as_m": (1.4, math.inf)}}, "finite number"),
    ({"prior": {"rho": (0.0, 1.1)}}, "rho must lie in [0, 1]"),
    ({"prior": {"albedo": (-0.1, 1.0)}}, "albedo must lie in [0, 1]"),
    ({"prior": {"rho_aba": (0.0, 1.5)}}, "rho_aba must lie in [0, 1]"),
    ({"prior": {"coupling": (0.5, 20.0)}}, "coupling must lie in [0, 10]"),
    ({"prior": {"scheme": "uniform"}}, "'reciprocal', 'independent' or 'explicit'"),
    ({"prior": {"albedos": (0.1, 1.0)}}, "Extra inputs are not permitted"),
    ({"frequencies_hz": ()}, "frequencies_hz is empty"),
    ({"frequencies_hz": (0.0,)}, "must be positive"),
    ({"frequencies_hz": (-12.5e6,)}, "must be positive"),
    ({"frequencies_hz": (math.nan,)}, "finite number"),
    ({"frequencies_hz": (12.5e6, NYQUIST_HZ)}, "Nyquist"),
    ({"frequencies_hz": (100e6,)}, "Nyquist"),
    ({"frequencies_hz": (12.5e6, 12.5e6)}, "duplicates"),
    ({"frequencies_hz": (30e3,)}, "less than one cycle"),
    ({"simulator": {"fidelity": "exact"}}, "'moment' or 'waveform'"),
    ({"simulator": {"noise_scale": -1.0}}, "greater than or equal to 0"),
    ({"simulator": {"noise": 1.0}}, "Extra inputs are not permitted"),
    ({"sensor": {"quantum_efficiency": 1.5}}, "less than or equal to 1"),
    ({"sensor": {"avalanche_gain": 0.5}}, "greater than or equal to 1"),
    ({"sensor": {"transit_time_s": 0.0}}, "greater than 0"),
    ({"sensor": {"integration_time_s": 6e-9}}, "at least two transit-time bins"),
    ({"dataset": {"samples": 0}}, "greater than or equal to 1"),
    ({"dataset": {"samples": 100, "chunk_rows": 200}}, "chunk_rows (200) is larger than samples (100)"),
    ({"dataset": {"test_fraction": 1.0}}, "less than 1"),
    ({"sensors": {}}, "Extra inputs are not permitted"),
]
INVALID_REPLACEMENT_IDS = [
    "negative_d_as", "zero_d_as", "negative_d_ab", "reversed_interval", "infinite_interval", "rho_above_one",
    "negative_albedo", "rho_aba_above_one", "coupling_above_max", "unknown_scheme", "unknown_prior_field",
    "no_frequencies", "zero_frequency", "negative_frequency", "nan_frequency", "frequency_at_nyquist",
    "frequency_above_nyquist", "duplicate_frequencies", "under_one_cycle", "unknown_fidelity",
    "negative_noise_scale", "unknown_simulator_field", "quantum_efficiency_above_one", "gain_below_one",
    "zero_transit_time", "integration_under_two_bins", "zero_samples", "chunk_larger_than_samples",
    "test_fraction_one", "unknown_section",
]


@pytest.mark.parametrize(("sections", "message"), INVALID_REPLACEMENTS, ids=INVALID_REPLACEMENT_IDS)
def test_config_replace__rejects_nonsense(config, sections, message):
    with pytest.raises(ValidationError) as info:
        config.replace(**sections)
    assert message in str(info.value)


def test_config_model_validate__rejects_nonsense():
    with pytest.raises(ValidationError, match="frequencies_hz is empty"):
        Config.model_validate({"frequencies_hz": []})
    with pytest.raises(ValidationError, match="Extra inputs are not permitted"):
        Config.model_validate({"sensor": {"gain": 1.0}})
    with pytest.raises(ValidationError, match="d_ab_m must be non-negative"):
        Config.model_validate({"prior": {"d_ab_m": [-1.0, 0.0]}})


@pytest.mark.parametrize("frequency_hz", [12.5e6, 31.25e6, 80e6, NYQUIST_HZ * (1 - 1e-9)])
def test_config__accepts_frequencies_below_nyquist(config, frequency_hz):
    assert config.replace(frequencies_hz=[frequency_hz]).frequencies_hz == (frequency_hz,)


@pytest.mark.parametrize("sections", [
    {"simulator": {"noise_scale": math.inf}},
    {"simulator": {"tia_noise_mean_electrons": math.nan}},
    {"simulator": {"background_mean_electrons": math.inf}},
    {"sensor": {"gamma_r_v2": math.inf}},
], ids=["noise_scale_inf", "tia_mean_nan", "background_inf", "gamma_r_inf"])
def test_config_replace__rejects_non_finite_values(config, sections):
    with pytest.raises(ValidationError):
        config.replace(**sections)


def test_config_replace__rejects_whole_cycles_without_a_whole_cycle_window(config):
    with pytest.raises(ValidationError, match="whole"):
        config.replace(frequencies_hz=[12.5e6 + 1], simulator={"whole_cycles": True})


# --- TOML files ------------------------------------------------------------------------------------------


def test_load_config__toml_overrides_apply(tmp_path):
    path = write_toml(tmp_path, """
frequencies_hz = [12.5e6, 25e6]

[simulator]
noise_scale = 0.5
whole_cycles = true

[prior]
scheme = "independent"
d_ab_m = [0.0, 0.1]

[dataset]
samples = 1000
chunk_rows = 250
""")
    config = load_config(path)
    assert config.frequencies_hz == (12.5e6, 25e6)
    assert config.simulator.noise_scale == 0.5 and config.simulator.whole_cycles
    assert config.prior.scheme == "independent" and config.prior.d_ab_m == (0.0, 0.1)
    assert (config.dataset.samples, config.dataset.chunk_rows) == (1000, 250)
    # everything else keeps its default
    default = Config()
    assert config.sensor == default.sensor
    assert config.prior.d_as_m == default.prior.d_as_m
    assert config.simulator.round_photons == default.simulator.round_photons
    assert config.dataset.seed == default.dataset.seed


def test_load_config__overrides_a_base_preset(tmp_path):
    config = load_config(write_toml(tmp_path, "[dataset]\nseed = 5\n"), base=preset("paper"))
    assert config.dataset.seed == 5
    assert config.dataset.samples == PAPER_SAMPLES


BAD_TOML = [
    ("[prior]\nd_as_m = [-1.0, 2.0]\n", "prior: d_as_m must be positive"),
    ("[prior]\nd_ab_m = [-0.05, 0.15]\n", "prior: d_ab_m must be non-negative"),
    ("frequencies_hz = []\n", "frequencies_hz is empty"),
    ("frequencies_hz = [0.0]\n", "frequencies_hz must be positive, got 0.0"),
    ("frequencies_hz = [-31.25e6]\n", "frequencies_hz must be positive"),
    ("frequencies_hz = [90e6]\n", "Nyquist"),
    ("[prior]\nrho_sas = [0.0, 1.5]\n", "rho_sas must lie in [0, 1]"),
    ("[prior]\nscheme = \"uniform\"\n", "prior.scheme:"),
    ("[simulator]\nnosie_scale = 0.0\n", "simulator.nosie_scale: unknown field"),
    ("[sensors]\ngamma_r_v2 = 0.2\n", "sensors: unknown field"),
    ("sensor = 3\n", "sensor:"),
    ("[simulator\nnoise_scale = 0\n", "is not valid TOML"),
    ("noise_scale = = 0\n", "is not valid TOML"),
    ("[dataset]\nsamples = \"many\"\n", "dataset.samples:"),
]
BAD_TOML_IDS = [
    "negative_d_as", "negative_d_ab", "no_frequencies", "zero_frequency", "negative_frequency", "above_nyquist",
    "rho_above_one", "unknown_scheme", "misspelt_field", "unknown_section", "section_not_a_table",
    "unclosed_table", "double_equals", "string_samples",
]


@pytest.mark.parametrize(("text", "message"), BAD_TOML, ids=BAD_TOML_IDS)
def test_load_config__rejects_nonsense_with_one_clear_line(tmp_path, text, message):
    path = write_toml(tmp_path, text, name="bad.toml")
    with pytest.raises(ConfigError) as info:
        load_config(path)
    text_of_error = str(info.value)
    assert message in text_of_error
    assert str(path) in text_of_error  # names the file
    assert "\n" not in text_of_error  # one line


def test_load_config__counts_further_problems(tmp_path):
    path = write_toml(tmp_path, "[simulator]\nfoo = 1\nbar = 2\nbaz = 3\n")
    with pytest.raises(ConfigError, match=r"\(and 2 more problems\)"):
        load_config(path)


def test_load_config__missing_and_undecodable_files(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        load_config(tmp_path / "absent.toml")
    binary = tmp_path / "binary.toml"
    binary.write_bytes(b"\xff\xfe\x00junk")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(binary)


def test_preset__quick_paper_and_unknown():
    assert preset("quick").dataset.samples == 20_000
    paper = preset("paper")
    assert (paper.dataset.samples, paper.dataset.test_fraction) == (PAPER_SAMPLES, 0.2)
    with pytest.raises(ConfigError, match="unknown preset 'huge'"):
        preset("huge")


# --- the hash ---------------------------------------------------------------------------------------------


def test_config_sha256__stable_and_hex(config):
    digest = config_sha256(config)
    assert len(digest) == 64 and all(c in "0123456789abcdef" for c in digest)
    assert config_sha256(Config()) == digest
    assert config_sha256(config.replace()) == digest
    assert config_sha256(config_from_json(config_json(config))) == digest


def test_config_sha256__toml_key_order_is_irrelevant(tmp_path):
    one = write_toml(tmp_path, """
frequencies_hz = [12.5e6, 31.25e6]
[simulator]
noise_scale = 0.5
round_photons = false
[prior]
d_ab_m = [0.0, 0.1]
scheme = "explicit"
""", name="one.toml")
    two = write_toml(tmp_path, """
frequencies_hz = [12500000, 31250000]
[prior]
scheme = "explicit"
d_ab_m = [0, 0.1]
[simulator]
round_photons = false
noise_scale = 0.5
""", name="two.toml")
    assert config_sha256(load_config(one)) == config_sha256(load_config(two))
    assert config_sha256(load_config(one)) != config_sha256(Config())


def _leaf_paths(tree: dict, prefix: tuple = ()) -> list[tuple]:
    paths = []
    for key, value in tree.items():
        if isinstance(value, dict):
            paths += _leaf_paths(value, (*prefix, key))
        else:
            paths.append((*prefix, key))
    return paths


def _perturbed(value: object, key: str) -> object:
    if isinstance(value, bool):
        return not value
    if key == "scheme":
        return "independent"
    if key == "fidelity":
        return "waveform"
    if key in ("d_as_distribution", "coupling_distribution"):
        return "uniform" if value == "log_uniform" else "log_uniform"
    if isinstance(value, int):
        return value - 1 if key == "chunk_rows" else value + 1
    if isinstance(value, float):
        return value * 0.99 if value else 0.01
    if isinstance(value, list):
        return [*value[:-1], value[-1] * 0.99]
    raise AssertionError(f"no perturbation for {key}={value!r}")


def test_config_sha256__any_changed_field_changes_the_hash(config):
    base = config.model_dump(mode="json")
    paths = _leaf_paths(base)
    assert len(paths) > 40
    digests = {config_sha256(config)}
    for path in paths:
        data = copy.deepcopy(base)
        node = data
        for key in path[:-1]:
            node = node[key]
        node[path[-1]] = _perturbed(node[path[-1]], path[-1])
        digests.add(config_sha256(Config.model_validate(data)))
    assert len(digests) == len(paths) + 1


@settings(max_examples=40, deadline=None, derandomize=True)
@given(noise_scale=st.floats(0.0, 10.0), seed=st.integers(0, 2**31), samples=st.integers(1, 10**6))
def test_config_sha256__equal_configs_equal_hashes(noise_scale, seed, samples):
    sections = {"simulator": {"noise_scale": noise_scale},
                "dataset": {"seed": seed, "samples": samples, "chunk_rows": 1}}
    a, b = Config().replace(**sections), Config().replace(**sections)
    assert config_sha256(a) == config_sha256(b)
    assert (config_sha256(a) == config_sha256(Config())) == (a == Config())


def test_resolve_config__fewer_samples_shrink_chunk_rows_unless_given():
    from mpi_lidar.config import resolve_config

    config = resolve_config(None, "quick", samples=300, seed=7)
    assert (config.dataset.samples, config.dataset.chunk_rows, config.dataset.seed) == (300, 300, 7)
    assert resolve_config(None, "quick") == resolve_config(None, "quick", samples=None)
    with pytest.raises(ConfigError, match=r"chunk_rows \(400\) is larger than samples \(300\)"):
        resolve_config(None, "quick", samples=300, chunk_rows=400)


# --- the d_AS distribution ----------------------------------------------------------------------------------

# SHA-256 of the default configuration as it was before PriorConfig.d_as_distribution existed (d_AS uniform over
# 1.4-2.4 m, PriorConfig's own defaults): a regression anchor, as datasets and model cards record this hash.
UNIFORM_PRIOR_CONFIG_SHA256 = "74ff96a9de35dc7698d118deff9fc47f530503f65ab46d9f1550a6ebc09925ff"


def test_prior_config__uniform_d_as_distribution_is_left_out_and_keeps_the_hash():
    uniform = Config(prior=PriorConfig())
    assert uniform.prior.d_as_distribution == "uniform" and uniform.prior.d_as_m == (1.4, 2.4)
    assert "d_as_distribution" not in config_json(uniform)
    assert config_sha256(uniform) == UNIFORM_PRIOR_CONFIG_SHA256
    assert config_sha256(Config(prior=PriorConfig(d_as_distribution="uniform"))) == UNIFORM_PRIOR_CONFIG_SHA256


def test_prior_config__log_uniform_is_written_changes_the_hash_and_round_trips():
    wide = Config(prior=PriorConfig(d_as_m=(0.5, 12.0), d_as_distribution="log_uniform"))
    assert '"d_as_distribution":"log_uniform"' in config_json(wide)
    assert config_from_json(config_json(wide)) == wide
    assert config_sha256(wide) != config_sha256(wide.replace(prior={"d_as_distribution": "uniform"}))


def test_load_config__log_uniform_needs_positive_distances_and_a_known_name(tmp_path):
    zero = write_toml(tmp_path, '[prior]\nd_as_m = [0.0, 12.0]\nd_as_distribution = "log_uniform"\n')
    with pytest.raises(ConfigError, match=r"d_as_m must be positive .*log-uniform d_as_distribution needs low > 0"):
        load_config(zero)
    unknown = write_toml(tmp_path, '[prior]\nd_as_distribution = "normal"\n', name="unknown.toml")
    with pytest.raises(ConfigError, match=r"prior\.d_as_distribution: .*'uniform' or 'log_uniform'"):
        load_config(unknown)
