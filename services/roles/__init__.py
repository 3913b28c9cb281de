"""The processes of a run (learner, worker, referee, monitor, router) and what only they use."""
