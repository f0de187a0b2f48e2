"""The chunked calibration on a Dask cluster: the same camera as one process, and one-line errors."""

import numpy as np
import pytest
from synthetic_sessions import synthetic_session
from test_calibration_chunked import SEED004, SEED004_NOMINAL, _split, assert_same_camera

from hostlink.calibration.distributed import DaskPasses, dask_client, map_sensors
from hostlink.calibration.run import calibrate_chunks
from hostlink.errors import UserError

pytest.importorskip("distributed")


@pytest.fixture(scope="module")
def client():
    # threads instead of processes: the same scheduling, serialisation of tasks aside, without process start-up time
    with dask_client("local", n_workers=2, processes=False) as c:
        yield c


def test_dask_pass_gives_the_camera_of_one_process(client):
    ss = synthetic_session(SEED004, 120, seed=5, misidentified_fraction=0.03)
    source = _split(ss.data, [0, 1, 30, 31, 77, 120])
    serial = calibrate_chunks(source, SEED004_NOMINAL)
    on_dask = calibrate_chunks(source, SEED004_NOMINAL, run_pass=DaskPasses(client))
    assert_same_camera(serial, on_dask)
    np.testing.assert_array_equal(on_dask.theta, serial.theta)  # results added in chunk order: bit for bit


def _sensor_focal(seed: int) -> float:
    ss = synthetic_session(SEED004, 30, seed=seed)
    return float(calibrate_chunks(_split(ss.data, [0, 30]), SEED004_NOMINAL).theta[0])


def test_fleet_runs_map_one_task_per_sensor_in_order(client):
    assert map_sensors(_sensor_focal, [(1,), (2,)], client) == [_sensor_focal(1), _sensor_focal(2)]


def test_unreachable_scheduler_is_a_one_line_error():
    with pytest.raises(UserError, match="cannot reach the Dask scheduler"):
        with dask_client("tcp://127.0.0.1:9", timeout_s=1):
            pass
