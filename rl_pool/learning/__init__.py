"""One member's learning: environments, episodes (rollouts), and an iteration's training and
evaluation. Built on :mod:`rl_pool.maths`; knows nothing of the pool directory."""
