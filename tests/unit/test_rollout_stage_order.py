"""The rollout serves per-stage links in arrival order; one shared link, or links without a file
descriptor (channels), in turn. Real pipes wrapped as the socket transport wraps its connection."""

from multiprocessing import Pipe

from infinirl.components.embodied_rollout import _RemoteEndpoint
from infinirl.components.env_link import _SocketLink


class NoFileno:
    """A link without a file descriptor, like the channel transport's."""

    def __init__(self, link):
        self.link = link

    def recv(self):
        return self.link.recv()


def links(n):
    pairs = [Pipe() for _ in range(n)]
    return [_SocketLink(ours) for ours, _ in pairs], [theirs for _, theirs in pairs]


def test_per_stage_socket_links_are_served_as_their_results_arrive():
    ours, theirs = links(3)
    endpoint = _RemoteEndpoint(ours, 3)
    assert endpoint.any_order
    theirs[2].send({"stage": 2})
    assert endpoint.ready([0, 1, 2]) == [2]  # stage 2 first, not stage 0
    theirs[0].send({"stage": 0})
    assert endpoint.ready([0, 1, 2]) == [0, 2]
    assert endpoint.recv(2) == {"stage": 2} and endpoint.recv(0) == {"stage": 0}
    theirs[1].send({"stage": 1})
    assert endpoint.ready([1]) == [1]


def test_one_shared_link_or_links_without_a_descriptor_are_served_in_turn():
    ours, _ = links(1)
    assert not _RemoteEndpoint(ours, 2).any_order
    ours, _ = links(2)
    assert not _RemoteEndpoint([NoFileno(link) for link in ours], 2).any_order
