"""The chunked calibration on a Dask cluster: the same camera as one process, and one-line errors."""

import numpy as np
import pytest
from synthetic_sessions import synthetic_session
from test_calibration_chunked import SEED004, SEED004_NOMINAL, _split, assert_same_camera

from hostlink.calibration.distributed import DaskPasses, dask_client, map_sensors
from hostlink.calibration.run import calibrate_archive, calibrate_chunks
from hostlink.errors import UserError
from hostlink.files.session import write_session
from hostlink.sky.simulate import seed004_config, simulate

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


def test_archive_on_a_local_cluster_of_two_processes_gives_the_camera_of_one_process(tmp_path):
    """What ``hostlink calibrate FILES --dask`` runs: a LocalCluster of two worker processes (not threads: the
    real path, ~5 s of start-up), the spooled chunks loaded on the workers from their file names; the results
    added in chunk order, so bit for bit."""
    session = simulate(seed004_config(frames=60, seed=43)).session
    half = int(session.frame_starts[30])
    files = [str(tmp_path / "night1.parquet"), str(tmp_path / "night2.parquet")]
    write_session(files[0], session.select(np.arange(half)))
    write_session(files[1], session.select(np.arange(half, len(session))))
    one, _ = calibrate_archive(files, SEED004_NOMINAL, chunk_frames=20)
    on_dask, _ = calibrate_archive(files, SEED004_NOMINAL, chunk_frames=20, dask="local", dask_workers=2)
    np.testing.assert_array_equal(on_dask.theta, one.theta)
    assert on_dask.rejected == one.rejected and len(on_dask.history) == len(one.history)
