import pytest

from infinirl.edge.credentials import issue_credentials


@pytest.fixture(scope="session")
def credentials(tmp_path_factory):
    """A cloud, two edges of its CA, and an edge of another CA (an impostor's files)."""
    issued = issue_credentials(tmp_path_factory.mktemp("pki"), edges=("edge-0", "edge-1"))
    issued["foreign"] = issue_credentials(tmp_path_factory.mktemp("pki-foreign"), edges=("edge-0",))["edge-0"]
    return issued
