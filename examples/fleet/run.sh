#!/usr/bin/env bash
# The fleet of docker-compose.yml as plain processes: a router, two robots, a base, each bridge
# in a ROS domain of its own (ROBOT1_DOMAIN, ROBOT2_DOMAIN, BASE_DOMAIN: 1, 2, 0). Ctrl-C stops
# them all.  Usage: examples/fleet/run.sh [ROSGATE]
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
rosgate="${1:-$here/../../.venv/bin/rosgate}"
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
pids=()
trap 'kill -INT "${pids[@]}" 2>/dev/null; wait' INT TERM EXIT
"$rosgate" router --listen tcp/127.0.0.1:7447 & pids+=($!)
ROS_DOMAIN_ID="${ROBOT1_DOMAIN:-1}" "$rosgate" run "$here/robot1.yaml" & pids+=($!)
ROS_DOMAIN_ID="${ROBOT2_DOMAIN:-2}" "$rosgate" run "$here/robot2.yaml" & pids+=($!)
ROS_DOMAIN_ID="${BASE_DOMAIN:-0}" "$rosgate" run "$here/base.yaml" & pids+=($!)
wait
