"""Two forked processes racing: the lock and folder-choice tests start them together and check both exit cleanly."""
import multiprocessing

FORK = multiprocessing.get_context("fork")  # the racers touch os, fcntl and pathlib only


def run_racers(target, args_of_each) -> None:
    """Start one forked process per ``args`` tuple of ``args_of_each`` on ``target``, wait for all (60 s each), and
    assert each exited 0."""
    racers = [FORK.Process(target=target, args=args) for args in args_of_each]
    for racer in racers:
        racer.start()
    for racer in racers:
        racer.join(timeout=60)
    assert [racer.exitcode for racer in racers] == [0] * len(racers)
