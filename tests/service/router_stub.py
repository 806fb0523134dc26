"""Stands in for zenohd (not installable from PyPI): a Zenoh peer listening on an endpoint that
clients connect to. Prints how many vertices messages it saw in ``seconds``, then exits."""
import sys
import time

import zenoh

endpoint, key, seconds = sys.argv[1], sys.argv[2], float(sys.argv[3])
conf = zenoh.Config()
conf.insert_json5("mode", '"peer"')
conf.insert_json5("scouting/multicast/enabled", "false")
conf.insert_json5("listen/endpoints", f'["{endpoint}"]')
session = zenoh.open(conf)
count = [0]
sub = session.declare_subscriber(key, lambda s: count.__setitem__(0, count[0] + 1))
print("ready", flush=True)
time.sleep(seconds)
print(count[0], flush=True)
session.close()
