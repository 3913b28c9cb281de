"""The algorithm: pure, without Zenoh or services.

Importing it pins the arithmetic first (`mam_core.arithmetic`), before numpy or torch load.
"""

from mam_core.arithmetic import pin as _pin

_pin()
