"""Registers the trainable kernel-prediction denoisers (imported lazily by the registry).

``wskp`` (6 RepVGG layers), ``wskp3`` (3 layers), ``wskp_mr`` (multi-resolution, Eq. 7),
``kp`` (direct 13x13 kernels, WSKP backbone), ``kp1`` (2 layers, k = 13), ``kp2``
(5 layers, k = 7).
"""

from __future__ import annotations

import dataclasses

from jaxden.denoisers import DenoiserDef, register
from jaxden.nn import wskp

_FEATURES = lambda config: wskp.WSKP_FEATURES  # noqa: E731


def _variant(cls, **defaults):
    """A config class with other defaults (so `wskp3` is its own registered name)."""
    fields = [(f.name, f.type, dataclasses.field(default=defaults.get(f.name, f.default)))
              for f in dataclasses.fields(cls)]
    return dataclasses.make_dataclass(cls.__name__, fields, frozen=True, namespace={"__doc__": cls.__doc__})


for name, description, cls, init, apply in (
    ("wskp", "weight-sharing kernel prediction, 6 RepVGG layers, kernels 3..13", wskp.WSKPConfig,
     wskp.wskp_init, wskp.wskp_denoise),
    ("wskp3", "weight-sharing kernel prediction, 3 RepVGG layers", _variant(wskp.WSKPConfig, num_layers=3),
     wskp.wskp_init, wskp.wskp_denoise),
    ("wskp_mr", "multi-resolution WSKP (3 scales, kernels 3 and 5, paper Eq. 7)", wskp.WSKPMRConfig,
     wskp.wskp_mr_init, wskp.wskp_mr_denoise),
    ("kp", "direct kernel prediction, 13x13, WSKP backbone (6 layers)", wskp.KPConfig,
     wskp.kp_init, wskp.kp_denoise),
    ("kp1", "direct kernel prediction, 2 layers, 13x13", _variant(wskp.KPConfig, num_layers=2),
     wskp.kp_init, wskp.kp_denoise),
    ("kp2", "direct kernel prediction, 5 layers, 7x7", _variant(wskp.KPConfig, num_layers=5, kernel_size=7),
     wskp.kp_init, wskp.kp_denoise),
):
    register(DenoiserDef(name=name, description=description, config_cls=cls, required=_FEATURES,
                         apply=apply, init=init))
