"""Stands in for zenohd (not installable from PyPI): a Zenoh peer listening on an endpoint that
clients connect to. Counts the messages on ``key`` until it has seen ``enough`` of them (an event
set by the subscriber) or ``seconds`` have passed, prints the count, then exits."""

import sys
import threading

import zenoh

endpoint, key, seconds = sys.argv[1], sys.argv[2], float(sys.argv[3])
enough = int(sys.argv[4]) if len(sys.argv) > 4 else None  # None: count for the whole `seconds`
conf = zenoh.Config()
conf.insert_json5("mode", '"peer"')
conf.insert_json5("scouting/multicast/enabled", "false")
conf.insert_json5("listen/endpoints", f'["{endpoint}"]')
session = zenoh.open(conf)
count, lock, done = [0], threading.Lock(), threading.Event()


def on_sample(_sample):
    with lock:
        count[0] += 1
        if enough is not None and count[0] >= enough:
            done.set()


sub = session.declare_subscriber(key, on_sample)
print("ready", flush=True)
done.wait(seconds)
with lock:
    print(count[0], flush=True)
session.close()
