"""ROS 2 over Zenoh without a ROS install, the way rmw_zenoh speaks it: message types from shipped definitions and
their RIHS01 hashes (types), keys, liveliness tokens and attachments (keys), a node with publishers (node), standard
messages from arrays (messages) and what an agent and the team server publish (publishers). The bridge form
(zenoh-bridge-ros2dds' plain keys) is kept as an option of the node."""

from .keys import Qos, parse_topic_key
from .node import Ros2Node, domain_id
from .publishers import AgentTopics, TeamTopics
from .types import dds_name, type_hash

__all__ = ["AgentTopics", "Qos", "Ros2Node", "TeamTopics", "dds_name", "domain_id", "parse_topic_key", "type_hash"]
