"""mapless: object-goal visual mapless navigation in the 120 real iTHOR floor plans.

Data flows one way: ``scenes`` (layouts) -> ``sim`` (pose graph, per-pose observations,
environments) -> ``models`` (agents) -> ``train`` / ``evaluate`` -> reports.
"""

__version__ = "0.1.0"
