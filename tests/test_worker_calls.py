"""``WorkerCalls``: gymnasium's worker processes called one at a time. A worker that answers
first is given its next call before a slower one has answered; answers come back in worker
order; a worker's error is raised with the others' calls left pending."""

from __future__ import annotations

import time

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.vector import AsyncVectorEnv

from jetbot_rt.train.vec_env import close_vector_env
from jetbot_rt.train.worker_calls import WorkerCalls


class Clock(gym.Env):
    observation_space = gym.spaces.Box(0, 1, (1,), np.float32)
    action_space = gym.spaces.Box(0, 1, (1,), np.float32)

    def __init__(self, index: int) -> None:
        self.index = index

    def reset(self, *, seed=None, options=None):
        return np.zeros(1, np.float32), {}

    def step(self, action):
        return np.zeros(1, np.float32), 0.0, False, False, {}

    def span(self, seconds: float) -> tuple[int, float, float]:
        """This worker's index and the monotonic clock (shared by the processes) before and
        after sleeping ``seconds``."""
        start = time.monotonic()
        time.sleep(seconds)
        return self.index, start, time.monotonic()

    def fail(self) -> None:
        raise ValueError(f"worker {self.index} failed")


def _clock(index: int) -> Clock:
    return Clock(index)


@pytest.fixture
def vector():
    envs = AsyncVectorEnv([lambda i=i: _clock(i) for i in range(2)], context="spawn")
    yield envs
    close_vector_env(envs, interrupted=True)


def test_the_first_worker_to_answer_gets_its_next_call_before_the_last_answers(vector):
    calls = WorkerCalls(vector)
    calls.send(0, "span", (0.0,))
    calls.send(1, "span", (1.0,))
    answered = []

    def then(index: int) -> None:
        answered.append(index)
        calls.send(index, "span", (0.0,))

    first = calls.gather(then)
    assert [index for index, _, _ in first] == [0, 1]  # in worker order
    assert answered == [0, 1]  # in the order they answered
    assert calls.last_spread is not None and calls.last_spread > 0.5
    second = calls.gather()
    assert calls.pending == set()
    # worker 0's next call ran while worker 1 still slept through its first
    assert second[0][1] < first[1][2] - 0.5


def test_a_worker_sent_a_second_call_before_the_first_is_read_is_refused(vector):
    calls = WorkerCalls(vector)
    calls.send_all("span", (0.0,))
    with pytest.raises(RuntimeError, match="worker 0 has a call unanswered"):
        calls.send(0, "span", (0.0,))
    assert [index for index, _, _ in calls.gather()] == [0, 1]


def test_a_workers_error_is_raised_and_the_others_stay_pending(vector):
    calls = WorkerCalls(vector)
    calls.send(0, "fail", ())
    calls.send(1, "span", (2.0,))
    with pytest.raises(ValueError, match="worker 0 failed"):
        calls.gather()
    assert calls.pending == {1}


def test_the_error_raised_is_the_answering_workers_though_another_queued_first(vector):
    """A worker queues its error, then answers; with two failing, the queue's first error can
    be the other worker's."""
    calls = WorkerCalls(vector)
    vector.error_queue.put((1, ValueError, "worker 1 failed", "trace of 1"))
    vector.error_queue.put((0, KeyError, "worker 0 failed", "trace of 0"))
    with pytest.raises(KeyError, match="worker 0 failed"):
        calls._raise(0)
    assert vector.error_queue.empty()
