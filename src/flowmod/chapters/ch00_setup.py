"""Chapter 00's backend: what the study runs on (package versions, the compute device) and
the parameters of the active profile, with the numbers the chapter glues."""

from __future__ import annotations

import pandas as pd

from flowmod import environment
from flowmod.params import Params, describe


def torch_version(versions: pd.DataFrame) -> str:
    """The torch version of :func:`flowmod.environment.versions`'s table."""
    return str(versions.set_index("package").loc["torch", "version"])


def device(params: Params) -> tuple[str, pd.DataFrame]:
    """(the device this run computes on, its table) for the profile's ``device`` setting
    (:func:`flowmod.environment.device_info`)."""
    info = environment.device_info(params.device)
    return info["device"], environment.device_table(info)


def parameters(params: Params) -> tuple[int, pd.DataFrame]:
    """(how many parameters the study has, every one with its value in this run, range,
    unit and readers: :func:`flowmod.params.describe`)."""
    table = describe(params)
    return len(table), table
