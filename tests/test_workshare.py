"""workshare.WorkShare: chunks of one thread's work that another thread helps with."""

from __future__ import annotations

import threading
import time

import pytest

from ribpull_core.workshare import WorkShare


def test_every_item_runs_once_and_a_helper_takes_some():
    share = WorkShare()
    done: dict[int, str] = {}
    started = threading.Event()

    def item(i: int) -> None:
        started.set()
        time.sleep(0.01)  # long enough for the helper to take some
        assert i not in done
        done[i] = threading.current_thread().name

    owner = threading.Thread(target=share.run, args=(item, range(40)), name="owner")
    owner.start()
    assert started.wait(5)
    assert share.help() is True  # took items until none was left
    owner.join(5)
    assert sorted(done) == list(range(40))
    assert set(done.values()) == {"owner", threading.current_thread().name}


def test_help_without_work_returns_at_once():
    share = WorkShare()
    assert share.help() is False
    share.run(lambda i: None, range(3))
    assert share.help() is False  # the work is over


def test_an_items_error_reaches_the_owner_even_when_a_helper_raised_it():
    share = WorkShare()
    ran: list[int] = []
    gate, holding = threading.Event(), threading.Event()

    def item(i: int) -> None:
        if i == 0:
            holding.set()
            gate.wait(5)  # the owner holds item 0 until the helper has raised on item 1
            return
        ran.append(i)
        if i == 1:
            gate.set()
            raise ValueError("bad chunk")

    errors: list[BaseException] = []

    def owner() -> None:
        try:
            share.run(item, range(100))
        except ValueError as e:
            errors.append(e)

    t = threading.Thread(target=owner)
    t.start()
    assert holding.wait(5)
    share.help()  # takes item 1 (the owner is on item 0) and raises there; help itself does not raise
    t.join(5)
    assert [str(e) for e in errors] == ["bad chunk"]
    assert len(ran) < 99  # the items not yet taken were not run


def test_an_owner_alone_runs_everything_in_order():
    seen: list[int] = []
    WorkShare().run(seen.append, range(5))
    assert seen == [0, 1, 2, 3, 4]
    with pytest.raises(KeyError):
        WorkShare().run(lambda i: {}[i], range(2))
