"""The folder lock (umrl.folder_lock): never held twice, even by two processes starting at the same instant; a refusal
names the holder; a killed holder frees it; a lock file that is not a regular file is refused by name."""
import os
import signal

import pytest
from racing import FORK, run_racers

from umrl.folder_lock import LOCK_NAME, FolderInUse, FolderLock, lock_folder, reserve_folder
from umrl.validation import InvalidValue

TRIALS = 50


def _race(folders, start, attempted, wins):
    """One racer: for each folder, wait for the other racer, try the lock, keep it until both have tried, release."""
    for trial, folder in enumerate(folders):
        start.wait()
        lock = FolderLock(folder)
        try:
            lock.acquire()
        except FolderInUse:
            pass
        else:
            with wins.get_lock():
                wins[trial] += 1
        attempted.wait()  # a winner still holds the lock while the other tries
        lock.release()


def test_two_processes_started_together_never_both_hold_the_lock(tmp_path):
    """Half the trials race in a folder that does not exist yet, half over a lock file a dead process left (the
    old pid lock failed both: an empty or stale lock counted as free)."""
    folders = [tmp_path / f"trial{i}" for i in range(TRIALS)]
    for folder in folders[1::2]:
        folder.mkdir()
        (folder / LOCK_NAME).write_text("pid 999999 on elsewhere since 2020-01-01T00:00:00\n")
    start, attempted, wins = FORK.Barrier(2), FORK.Barrier(2), FORK.Array("i", TRIALS)
    run_racers(_race, [(folders, start, attempted, wins)] * 2)
    assert list(wins) == [1] * TRIALS  # one holder per trial: never both, never neither


def test_a_second_holder_is_refused_naming_the_first(tmp_path):
    with FolderLock(tmp_path) as lock:
        assert lock.path.read_text().startswith(f"pid {os.getpid()} on ")
        with pytest.raises(FolderInUse, match=rf"output_dir {tmp_path} is in use by this process \(pid {os.getpid()}"
                                              r" on .* since 20\d\d-.*\): close the trainer .*choose another "
                                              "output_dir or wait"):
            FolderLock(tmp_path).acquire()
    assert lock.path.exists() and lock.path.read_text() == ""  # released, emptied, never deleted
    FolderLock(tmp_path).acquire().release()


def test_another_process_is_named_and_its_death_frees_the_lock(tmp_path):
    held = FORK.Event()

    def hold():
        FolderLock(tmp_path).acquire()
        held.set()
        signal.pause()

    holder = FORK.Process(target=hold)
    holder.start()
    try:
        assert held.wait(timeout=30)
        with pytest.raises(FolderInUse, match=rf"in use by pid {holder.pid} on .* since "):
            FolderLock(tmp_path).acquire()
    finally:
        os.kill(holder.pid, signal.SIGKILL)
        holder.join()
    FolderLock(tmp_path).acquire().release()  # no stale lock: the kernel dropped it with the process


def test_a_reserved_lock_is_taken_over_once(tmp_path):
    reserved = reserve_folder(FolderLock(tmp_path).acquire())
    assert lock_folder(tmp_path) is reserved  # the run the Hydra callback locked the folder for
    with pytest.raises(FolderInUse):
        lock_folder(tmp_path)  # anyone after it is refused
    reserved.release()


@pytest.mark.parametrize("kind", ["folder", "symlink", "fifo"])
def test_a_lock_file_that_is_not_a_regular_file_is_refused_by_name(tmp_path, kind):
    path = tmp_path / LOCK_NAME
    if kind == "folder":
        path.mkdir()
    elif kind == "symlink":
        path.symlink_to(tmp_path / "elsewhere")
    else:
        os.mkfifo(path)
    with pytest.raises(InvalidValue, match=rf"output_dir: got '{tmp_path}' \({path}: .*\); expected a folder whose "
                                           f"{LOCK_NAME} is a regular file"):
        FolderLock(tmp_path).acquire()
    assert not (tmp_path / "elsewhere").exists()
