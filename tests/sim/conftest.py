"""Ray on loopback for the modules that scale out (``usefixtures("ray_environment")``)."""

import pytest
from ray._private import ray_constants
from ray.cluster_utils import Cluster


@pytest.fixture(scope="module")
def ray_environment():
    """Clusters on loopback, without token authentication (a cluster without it is what
    warns), and no RAY_ADDRESS from outside."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("RAY_AUTH_MODE", "disabled")
        patch.delenv("RAY_ADDRESS", raising=False)
        # Ray turns a loopback address into the machine's reachable one, unless clusters
        # are off (as on macOS); off, a driver finds the test's cluster on 127.0.0.1.
        patch.setattr(ray_constants, "ENABLE_RAY_CLUSTER", False)
        yield


@pytest.fixture(scope="module")
def cluster(ray_environment):
    """Two nodes of one CPU each, on loopback, shared by the module's tests."""
    nodes = Cluster(
        initialize_head=True, head_node_args={"num_cpus": 1, "node_ip_address": "127.0.0.1"}
    )
    nodes.add_node(num_cpus=1, node_ip_address="127.0.0.1")
    nodes.wait_for_nodes()
    yield nodes
    nodes.shutdown()
