"""The settings of a fusion run, resolved with the drive (``fieldlog fuse``, ``replay``, ``view``, ``evaluate``,
``batch``): the input map, the ``FusionConfig`` and where each setting came from, the drive's mounting.

Settings (``FusionConfig``): ``--config FILE`` reads the ``[fusion]`` table of a TOML file (other tables are
ignored, so a scenario file works too), e.g.::

    [fusion]
    gyro_noise_dps_rthz = 0.0097     # any FusionConfig field; lists for tuples
    lever_arm_b = [0.0, 0.5, 1.2]
    imu = "tactical"                 # an IMU grade of fusion.imugrade, and/or its datasheet keys:
    gyro_arw_deg_rth = 0.003         # deg/sqrt(h), gyro_bias_instability_dph with gyro_bias_corr_time_s, ...
    [fusion.predictor]               # fusion.predictors.PredictorConfig
    centres = 12

Without it, the drive's own ``fusion.config`` metadata record (what ``fieldlog sim`` stored from the scenario's
[fusion] table), else the defaults (``drive_config``). An explicit ``--config`` replaces the drive's record as
a whole; ``--outage`` replaces the outages of either.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from fieldlog.acquire import calib
from fieldlog.drive import metavalue
from fieldlog.drive.files import DriveSpec, label
from fieldlog.drive.reader import read_metadata
from fieldlog.drive.tables import ConfigError, TomlFile, from_table, typed_value
from fieldlog.fusion import imugrade
from fieldlog.fusion.config import FLAT_KEYS, FusionConfig, known_keys
from fieldlog.replay import inputs as inputs_mod
from fieldlog.replay.inputs import InputMap, InputSpec

BLOCK_S = 60.0  # s of log time per input block: the rows do not depend on it but for rounding (the engine, the
# installation's rate integral and the odometry carry over block ends), and longer blocks spread each block's fixed
# costs (reading, passing it between processes, encoding the rows) over more rows


def parse_outage(text: str) -> tuple[float, float]:
    """``START:LEN`` in seconds from the drive's first IMU sample -> (start_s, length_s)."""
    try:
        a, b = text.split(":")
        start, length = float(a), float(b)
    except ValueError:
        raise ValueError(f"--outage expects START:LEN in seconds, got {text!r}") from None
    if not (math.isfinite(start) and math.isfinite(length) and start >= 0.0 and length > 0.0):
        raise ValueError(f"--outage {text!r}: need START >= 0 and LEN > 0")
    return start, length


def fusion_config(table: dict[str, Any]) -> FusionConfig:
    """``FusionConfig`` from a ``[fusion]`` table of flat keys (``fusion.config``), each value converted by
    ``drive.tables.typed_value`` and the whole checked by ``FusionConfig.validate``; a bad key or value raises
    ConfigError naming it, e.g. ``[fusion] gyro_nosie_dps_rthz: unknown key; known keys: ...``."""
    try:
        table = imugrade.settings(table)
    except ValueError as e:
        raise ConfigError(f"[fusion] {e}") from None
    bad = sorted(set(table) - set(known_keys()))
    if bad:
        raise ConfigError(f"[fusion] {', '.join(bad)}: unknown key; known keys: {', '.join(sorted(known_keys()))}")
    defaults = FusionConfig()
    try:
        return FusionConfig.from_flat(**{k: typed_value("fusion", k, v, defaults.get(k))
                                         for k, v in table.items()}).validate()
    except ValueError as e:
        raise ConfigError(str(e)) from None


def load_fusion_config(config: TomlFile) -> FusionConfig:
    """``--config FILE``: the ``[fusion]`` table of a TOML file; ConfigError with one line naming the problem."""
    if not isinstance(config.tables.get("fusion"), dict):
        raise ConfigError(f"config file {config}: no [fusion] table")
    return fusion_config(config.tables["fusion"])


def load_input_spec(config: TomlFile | None) -> InputSpec:
    """The ``[input]`` table of a config file (``replay.inputs.InputSpec``: imu_topic, fix_topic, vel_topic,
    imu_frame); an empty spec without a file or table."""
    if config is None:
        return InputSpec()
    table = config.tables.get("input", {})
    if not isinstance(table, dict):
        raise ConfigError(f"config file {config}: [input] must be a table")
    for k, v in table.items():
        if not isinstance(v, str):
            raise ConfigError(f"[input] {k}: expected a string, got {v!r}")
    spec = from_table(InputSpec, "input", table)
    if spec.imu_frame is not None and spec.imu_frame.lower() not in ("rfu", "flu", "frd"):
        raise ConfigError(f"[input] imu_frame: one of rfu, flu, frd, got {spec.imu_frame!r}")
    return spec


def input_map(drive: DriveSpec, config: TomlFile | None, spec: InputSpec | None) -> InputMap:
    """``replay.inputs.resolve`` of the config's ``[input]`` table overridden by ``spec`` (the options), each
    input's source naming where it was given."""
    table, spec = load_input_spec(config), spec or InputSpec()
    given = {k: f"[input] of {config}" for k in table.given() if k not in spec.given()}
    return inputs_mod.resolve(drive, table.merged(spec), given)


@dataclass
class Settings:
    """What a fusion run uses: the FusionConfig, the input map, and where each setting came from."""

    config: FusionConfig
    inputs: InputMap
    sources: dict[str, str]  # FusionConfig field -> "--config FILE", "the drive's record", "/tf_static", "default"

    def lines(self, drive: DriveSpec) -> list[str]:
        """The settings grouped by where they came from; a warning when another logger's drive runs on the
        default sensor figures or lever arm."""
        out = [self.inputs.describe()]
        groups: dict[str, list[str]] = {}
        for k, src in self.sources.items():
            groups.setdefault(src, []).append(f"{k}={_show(self.config.get(k))}")
        for src in sorted(groups, key=lambda x: x == "default"):
            out.append(f"fusion settings ({src}): " + ", ".join(groups[src]))
        defaulted = [k for k in SENSOR_KEYS if self.sources[k] == "default"]
        if not self.inputs.native and defaulted:
            out.append(f"warning: {label(drive)} is from another logger and runs on default {', '.join(defaulted)}: "
                       "give its own figures in the [fusion] table of --config")
        return out


# the figures of a particular car and IMU: a default is a guess
SENSOR_KEYS = ("lever_arm_b", "gyro_noise_dps_rthz", "accel_noise_ug_rthz", "gyro_bias_rw_dps_rts",
               "accel_bias_rw_ug_rts", "gyro_scale_factor_ppm", "gyro_misalignment_mrad")


def _show(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:g}"
    if isinstance(v, tuple):
        return "(" + ", ".join(_show(x) for x in v) + ")"
    return str(v) if v != "" else "none"


def settings(drive: DriveSpec, config: TomlFile | None = None,
             spec: InputSpec | None = None, outages: tuple[tuple[float, float], ...] | None = None) -> Settings:
    """The settings of a fusion run and their sources: the input map (``replay.inputs.resolve`` of the config's
    [input] table overridden by ``spec``), the FusionConfig from ``--config``'s [fusion] table (replacing the
    drive's record as a whole), else the drive's ``fusion.config`` record, else the defaults; the lever arm from
    the drive's /tf_static when neither gives it; ``outages`` (``--outage``) replace the config's."""
    imap = input_map(drive, config, spec)
    table = config.tables.get("fusion") if config else None
    if table is None:
        table = drive_table(drive)
        where = "the drive's record"
    else:
        where = f"--config {config}"
    try:
        cfg = fusion_config(table)
    except (ValueError, TypeError) as e:
        if config:
            raise
        raise ValueError(f"{label(drive)}: its fusion.config record: {e}") from None
    given = set(imugrade.settings(table))  # an IMU grade's or datasheet keys' settings count as given
    derived = imugrade.sources(table)
    sources = {f: (f"{where}, {derived[f]}" if f in derived else where if f in given else "default")
               for f in FLAT_KEYS}
    sources["predictor"] = where if "predictor" in given else "default"
    if "lever_arm_b" not in given and imap.lever_arm_b is not None:
        cfg = cfg.replace(lever_arm_b=tuple(float(x) for x in imap.lever_arm_b), lever_arm_frame="rfu")
        sources["lever_arm_b"] = sources["lever_arm_frame"] = inputs_mod.TF_STATIC
    if outages:
        cfg = cfg.replace(outages=tuple(outages))
        sources["outages"] = "--outage"
    return Settings(cfg, imap, sources)


def installation_applies(config: FusionConfig, inputs: InputMap) -> bool:
    """Whether ``fuse`` estimates the installation first: ``[fusion] estimate_installation`` and a car aid that
    uses it, the NHC or the odometer with a wheel-speed topic (its estimators assume a car, heading = course; an
    aircraft's is not).

    Parameters
    ----------
    config : the settings of the run.
    inputs : the drive's topics.

    Returns
    -------
    bool
    """
    a = config.aids
    return a.estimate_installation and (a.nhc or (a.odometer and inputs.odom_topic is not None))


def drive_config(drive: DriveSpec) -> FusionConfig:
    """The drive's ``fusion.config`` metadata record (a simulated drive's scenario [fusion] table) as a
    FusionConfig; the defaults when the drive has none."""
    table = drive_table(drive)
    try:
        return fusion_config(table)
    except (ValueError, TypeError) as e:
        raise ValueError(f"{label(drive)}: its fusion.config record: {e}") from None


def drive_table(drive: DriveSpec) -> dict[str, Any]:
    """The drive's ``fusion.config`` metadata record as a [fusion] table; ValueError naming the drive when a
    value is not one (damaged metadata)."""
    out = {}
    for k, v in read_metadata(drive).get("fusion.config", {}).items():
        try:
            out[k] = metavalue.load(v)
        except ValueError as e:
            raise ValueError(f"{label(drive)}: its fusion.config record, {k}: {e}") from None
    return out


def drive_mounting(drive: DriveSpec) -> calib.Mounting:
    """The mounting in the drive's calibration record (zeros when the drive has none, e.g. a foreign bag)."""
    toml = read_metadata(drive).get("calibration", {}).get("toml")
    return calib.Calibration.from_toml(toml).mounting if toml else calib.Mounting()
