"""The agent layer between models and both trainers and the evaluator: how a policy acts
(:mod:`~mapless.agent.acting`) and how a recurrent policy is re-evaluated over a recorded segment
(:mod:`~mapless.agent.sequence`)."""
