"""Active design: which reach to ask for next, chosen from a method's current posterior draws.

    rank_goals(task, result, candidates, *, seed, budget) -> DesignInfo (every candidate, best first)
    next_goal(task, result, candidates, *, seed, budget) -> (goal (3,), DesignInfo)
"""

from camo_sbi.design.criterion import CRITERIA, DesignInfo, next_goal, rank_goals

__all__ = ["CRITERIA", "DesignInfo", "next_goal", "rank_goals"]
