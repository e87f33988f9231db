"""The backward's gradient block (render/gradient_block.py) and its state lookup (device_state.backward_state)."""
import threading

import torch

from warpgs.render.device_state import backward_state, device_state
from warpgs.render.gradient_block import FEATURES, OPACITIES, GradientBlock


def _saved(n=5, nf=2):
    return [torch.randn(n, 3), torch.randn(n, 4), torch.randn(n, 3), torch.randn(n), torch.randn(n, 4, 3),
            torch.randn(n, nf)]


def test_addresses_are_the_views_the_backward_returns():
    needs = (True, False, True, True, False, True, False, True)
    block = GradientBlock(_saved(), ((4, 4), (3, 3)), needs)
    grads, g_opac, g_feat = block.views()
    assert block.address(OPACITIES) == g_opac.data_ptr()
    assert block.address(FEATURES) == g_feat.data_ptr()
    assert [g is not None for g in grads] == list(needs)
    assert [tuple(g.shape) for g in grads if g is not None] == [(5, 3), (5, 3), (5,), (5, 2), (3, 3)]
    assert all(g.is_contiguous() and not g.any() for g in grads if g is not None)
    # parts do not overlap: writing one leaves the others zero
    grads[0].fill_(1.0)
    assert not g_opac.any() and not grads[2].any() and not grads[7].any()


def test_opacity_and_feature_parts_exist_when_their_inputs_need_no_gradient():
    block = GradientBlock(_saved(), ((4, 4), (3, 3)), (True,) + (False,) * 7)
    grads, g_opac, g_feat = block.views()
    assert grads[3] is None and grads[5] is None
    assert g_opac.shape == (5,) and g_feat.shape == (5, 2)
    assert block.address(OPACITIES) == g_opac.data_ptr()


def test_backward_state_is_this_threads_state_for_the_forwards_key():
    forward = device_state(torch.device("cpu"))
    assert backward_state(forward) is forward
    seen = []
    worker = threading.Thread(target=lambda: seen.append((backward_state(forward), device_state(torch.device("cpu")))))
    worker.start()
    worker.join()
    other, own = seen[0]
    assert other is own and other is not forward  # a workspace per thread, as a forward on that thread would get
    assert other.key == forward.key
