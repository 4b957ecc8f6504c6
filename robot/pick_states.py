"""The pick cycle's steps (``CycleState``) and where each may go next (``TRANSITIONS``): the state machine that
``robot.picker.Picker`` runs, one handler per step, and checks every step against."""

from __future__ import annotations

from enum import Enum

from robot.pick_report import Stage


class CycleState(Enum):
    """The steps of one cycle (what each does and when: ``robot.picker``'s module docstring)."""

    CAPTURE = "capture"  # take a frame
    PERCEIVE = "perceive"  # estimate the parts, leave out those given up
    PLAN = "plan"  # plan grasps
    REFINE = "refine"  # nothing safe: have the perception refine more parts
    DECIDE = "decide"  # grasps to try, or nothing safe (nudge or stop), or no part in the bin
    CHECK_EMPTY = "check_empty"  # no part estimated in the bin: does the depth agree?
    GIVE_UP = "give_up"  # every part seen is where too many attempts failed
    NUDGE = "nudge"  # drag a part clear of a wall or a neighbour, if one can be
    NEXT_GRASP = "next_grasp"  # start an attempt on the next planned grasp
    APPROACH = "approach"
    GRASP = "grasp"
    VERIFY = "verify"
    PLACE = "place"
    ATTEMPT_END = "attempt_end"  # picked: done; refused: the next grasp; else look again
    RETREAT = "retreat"  # back to the observe pose
    DONE = "done"


_S = CycleState
#: Where each step may go next.
TRANSITIONS: dict[CycleState, tuple[CycleState, ...]] = {
    _S.CAPTURE: (_S.PERCEIVE,),
    _S.PERCEIVE: (_S.PLAN, _S.CHECK_EMPTY, _S.GIVE_UP, _S.CAPTURE),
    _S.PLAN: (_S.DECIDE, _S.REFINE),
    _S.REFINE: (_S.PLAN, _S.DECIDE, _S.GIVE_UP),
    _S.DECIDE: (_S.NEXT_GRASP, _S.NUDGE, _S.CHECK_EMPTY),
    _S.CHECK_EMPTY: (_S.DONE,),
    _S.GIVE_UP: (_S.DONE,),
    _S.NUDGE: (_S.RETREAT, _S.DONE, _S.CAPTURE),
    _S.NEXT_GRASP: (_S.APPROACH,),
    _S.APPROACH: (_S.GRASP, _S.ATTEMPT_END),
    _S.GRASP: (_S.VERIFY, _S.ATTEMPT_END),
    _S.VERIFY: (_S.PLACE, _S.ATTEMPT_END),
    _S.PLACE: (_S.ATTEMPT_END,),
    _S.ATTEMPT_END: (_S.NEXT_GRASP, _S.RETREAT, _S.DONE),
    _S.RETREAT: (_S.DONE,),
    _S.DONE: (),
}
#: The steps of an attempt, and the stage an attempt that ends there is recorded with.
ATTEMPT_STAGES = {_S.APPROACH: Stage.APPROACH, _S.GRASP: Stage.GRASP, _S.VERIFY: Stage.VERIFY, _S.PLACE: Stage.PLACE}
