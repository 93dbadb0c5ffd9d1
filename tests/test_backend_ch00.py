"""Chapter 00's backend (``flowmod.chapters.ch00_setup``), quick tests for mutation testing:
the torch version the chapter glues, the device and its table, and the parameter count and
table. Each expected value is written here by hand or read straight off torch, platform and
the ``Params`` model, so that a one-line change of the backend (a key, a returned value, the
device asked for) fails a test. No world, no run folder.
"""

from __future__ import annotations

import platform

import pandas as pd
import pytest
import torch

from flowmod.chapters import ch00_setup as ch00
from flowmod.params import Params, load_profile


def test_torch_version_is_the_torch_row_of_the_versions_table_as_a_string():
    """The version is read off the ``torch`` row (not the first or another row) of the
    ``package``/``version`` table, and always comes back as a string."""
    versions = pd.DataFrame({"package": ["python", "numpy", "torch", "pandas"],
                             "version": ["3.11.2", "2.1.0", "2.5.1", "3.0.0"]})
    assert ch00.torch_version(versions) == "2.5.1"
    numeric = pd.DataFrame({"package": ["torch", "numpy"], "version": [2.5, 1.26]})
    got = ch00.torch_version(numeric)
    assert got == "2.5" and isinstance(got, str)


def test_device_on_the_cpu_names_it_and_tables_what_it_runs_on():
    """``device: cpu``: the device is "cpu" and its table lists, in order, the device, the
    processor and torch's thread count, every value as text."""
    p = load_profile("smoke", device="cpu")
    name, table = ch00.device(p)
    assert name == "cpu"
    assert list(table.columns) == ["what", "value"]
    assert table["what"].tolist() == ["device", "cpu", "torch_threads"]
    assert table["value"].tolist() == ["cpu", platform.processor() or platform.machine(),
                                       str(torch.get_num_threads())]


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
def test_device_asks_for_the_profile_s_device_not_the_automatic_one():
    """The profile's ``device`` setting is the one asked for: ``cuda`` on a machine without
    CUDA is an error (the automatic choice would quietly run on the CPU)."""
    with pytest.raises(RuntimeError, match="no CUDA device"):
        ch00.device(load_profile("smoke", device="cuda"))
    name, _ = ch00.device(load_profile("smoke", device="auto"))
    assert name == "cpu"


def test_parameters_counts_and_tables_every_parameter_of_the_study():
    """(the number of parameters, their table): one row per field of ``Params`` in its
    order, with this run's value as text, its description and its readers."""
    p = load_profile("smoke", seed=7)
    n, table = ch00.parameters(p)
    fields = list(Params.model_fields)
    assert n == len(fields) == len(table)
    assert list(table.columns) == ["parameter", "value", "description", "read by"]
    assert table["parameter"].tolist() == fields
    row = table.set_index("parameter").loc["seed"]
    assert row["value"] == "7"
    assert row["description"] == Params.model_fields["seed"].description
