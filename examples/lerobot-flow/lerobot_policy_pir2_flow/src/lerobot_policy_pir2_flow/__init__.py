"""LeRobot policy plugin ``pir2_flow``: a πR² flow policy trained with pir2's draws.

Installed next to ``lerobot``, it registers itself when LeRobot imports third-party plugins
(``lerobot-train --policy.type=pir2_flow ...``). ``python -m lerobot_policy_pir2_flow.export``
turns a trained policy into a checkpoint pir2's real-time runtime runs (``pir2 eval``).
"""

from .configuration_pir2_flow import Pir2FlowConfig
from .modeling_pir2_flow import Pir2FlowPolicy
from .processor_pir2_flow import make_pir2_flow_pre_post_processors

__all__ = ["Pir2FlowConfig", "Pir2FlowPolicy", "make_pir2_flow_pre_post_processors"]
