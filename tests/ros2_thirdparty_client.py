"""A ROS 2 node written with `zenoh-ros2-sdk` (a third party's rmw_zenoh client, no ROS 2 installed), run
by `test_ros2_thirdparty.py` in a process of its own: it discovers the served world's topics, reads their
type hashes, subscribes to /joint_states and /clock, and commands the arm on /arm/joint_commands. Prints
what it saw as one JSON line. Arguments: the server's port, the folder of message definitions."""

from __future__ import annotations

import json
import sys
import time

import numpy as np
from zenoh_ros2_sdk import ROS2Publisher, ROS2Subscriber, get_registry, get_topic_info, get_topic_names_and_types


def main(port: int, messages: str) -> None:
    get_registry(messages)  # the definitions shipped with the tests: nothing is cloned from the network
    where = dict(router_ip="127.0.0.1", router_port=port)
    topics = dict(get_topic_names_and_types(timeout=2.0, **where))
    info = get_topic_info("/joint_states", verbose=True, timeout=2.0, **where)
    states: list = []
    clocks: list = []
    subs = [ROS2Subscriber("/joint_states", "sensor_msgs/msg/JointState", states.append, **where),
            ROS2Subscriber("/clock", "rosgraph_msgs/msg/Clock", clocks.append, **where)]
    deadline = time.monotonic() + 20
    while (len(states) < 3 or not clocks) and time.monotonic() < deadline:
        time.sleep(0.02)
    pub = ROS2Publisher("/arm/joint_commands", "std_msgs/msg/Float64MultiArray", **where)
    time.sleep(0.5)  # matched with the world's subscriber
    layout = pub.session_mgr.store.types["std_msgs/msg/MultiArrayLayout"](dim=[], data_offset=0)
    pub.publish(layout=layout, data=np.array([0.3, 0.5, -0.4]))
    time.sleep(0.5)
    last = states[-1] if states else None
    print(json.dumps({
        "topics": {name: list(types) for name, types in topics.items()},
        "joint_states_hash": info.publishers[0].type_hash if info and info.publishers else None,
        "joint_states_node": info.publishers[0].node_name if info and info.publishers else None,
        "received": len(states), "clocks": len(clocks),
        "names": list(last.name) if last is not None else None,
        "positions": [float(x) for x in last.position] if last is not None else None,
        "stamp": [last.header.stamp.sec, last.header.stamp.nanosec] if last is not None else None,
    }), flush=True)
    pub.close()
    for sub in subs:
        sub.close()


if __name__ == "__main__":
    main(int(sys.argv[1]), sys.argv[2])
