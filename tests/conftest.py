import pytest
import torch

torch.set_num_threads(1)  # small tensors: one thread is fastest, and CI has two cores

from deform.io.recordings import find_data_root


@pytest.fixture(scope="session")
def data_root():
    root = find_data_root()
    if root is None or not (root / "DLO1").is_dir():
        pytest.skip("DEFORM dataset not available (set DEFORM_DATA)")
    return root


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)
