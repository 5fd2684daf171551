"""Helpers the perception worker processes of tests/test_realtime.py import (by module name:
a spawned worker gets this process's sys.path)."""

import os
import time


def slowed(seconds, fn, *args):
    """``fn(*args)`` after sleeping ``seconds``: a perception step made slow."""
    time.sleep(seconds)
    return fn(*args)


def pid_and(value):
    """(this process's id, value): where a job ran."""
    return os.getpid(), value


def fail(message):
    raise ValueError(message)


def make_counter(start):
    """A shared object: a list whose length counts the jobs that used it."""
    return [start]


def count(counter):
    counter.append(len(counter))
    return len(counter)


def exit_now(code):
    os._exit(code)


def identity(value):
    return value


def size_of(value):
    return len(value)
