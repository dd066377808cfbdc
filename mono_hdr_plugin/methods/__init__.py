"""Methods that lift any backbone to HDR: Mono-HDR (the meta-algorithm), its ablations, and
the HDR-NeRF / HDR-GS style baselines, all in the same wrapper role.

A method takes a backbone's LdrFeatures for one view, renders LDR and HDR with ONE call of
`features.composite`, and computes the training loss. It never looks inside the backbone.
Methods are plugins: `@register_method("name")` on an HdrMethod subclass (methods/base.py), or
the `mono_hdr.methods` entry-point group; `mono-hdr methods` lists them. Each built-in method is
one module here, and importing this package registers them.
"""

# The import order is the registration order, which `mono-hdr methods` lists: keep it unsorted.
# isort: off
from mono_hdr_plugin.methods import mono  # noqa: F401 - registers "mono"
from mono_hdr_plugin.methods import ablations  # noqa: F401 - registers "mlp-l2h", "mlp-h2l", "no-h2l"
from mono_hdr_plugin.methods import hdr_nerf  # noqa: F401 - registers "hdr-nerf"
from mono_hdr_plugin.methods import hdr_gs  # noqa: F401 - registers "hdr-gs"
# isort: on
