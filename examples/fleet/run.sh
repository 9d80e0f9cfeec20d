#!/usr/bin/env bash
# The fleet of docker-compose.yml as plain processes: a router, two robots, a base, each bridge
# in a ROS domain of its own (ROBOT1_DOMAIN, ROBOT2_DOMAIN, BASE_DOMAIN: 1, 2, 0). Mutual TLS
# with certificates made here once (certs/, beside this script), and the router's access
# control: each robot sends and takes only on fleet/<its name>/**. Ctrl-C stops them all.
# Usage: examples/fleet/run.sh [ROSGATE]
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
rosgate="${1:-$here/../../.venv/bin/rosgate}"
cd "$here"                              # certs are made and read here (the router's --tls certs)
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
names=(router robot1 robot2 base)
missing=()
for name in "${names[@]}"; do
    [[ -f certs/ca.pem && -f certs/$name.pem && -f certs/$name.key ]] || missing+=("$name")
done
if [[ ${#missing[@]} -gt 0 ]]; then     # the CA is made once and reused: certs/ca.key
    "$rosgate" certs --out certs "${missing[@]}"
fi
pids=()
trap 'kill -INT "${pids[@]}" 2>/dev/null; wait' INT TERM EXIT
"$rosgate" router --tls certs --listen tls/127.0.0.1:7447 --base base \
    --robot robot1 --robot robot2 & pids+=($!)
for _ in $(seq 300); do                 # the bridges are zenoh clients: the router first
    (exec 3<>/dev/tcp/127.0.0.1/7447) 2>/dev/null && break
    kill -0 "${pids[0]}" 2>/dev/null || { echo "run.sh: the router stopped" >&2; exit 1; }
    sleep 0.1
done
ROS_DOMAIN_ID="${ROBOT1_DOMAIN:-1}" "$rosgate" run robot1.yaml & pids+=($!)
ROS_DOMAIN_ID="${ROBOT2_DOMAIN:-2}" "$rosgate" run robot2.yaml & pids+=($!)
ROS_DOMAIN_ID="${BASE_DOMAIN:-0}" "$rosgate" run base.yaml & pids+=($!)
wait
