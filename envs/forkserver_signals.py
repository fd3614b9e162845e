"""Imported by the simulators' forkserver (in its preload list), not by user code: the server, and the
workers it forks, ignore the run's stop signals, which the main process handles
(:func:`l1flow_rl.envs.workers.signal_safe_factory` says why). The server still exits with the
main process: it stops when its pipe from the main process closes. Every process the server forks
inherits the ignored signals: a pool that the main process does not stop itself restores them
(``l1flow_rl.envs.robosuite.pool.worker_pool``, with :func:`~l1flow_rl.envs.workers.restore_stop_signals`).
"""

from l1flow_rl.envs.workers import ignore_stop_signals

ignore_stop_signals()
