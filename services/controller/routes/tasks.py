"""``GET /tasks``: the built-in control-synthesis tasks and their parameters."""

from __future__ import annotations

from fastapi import APIRouter

from neuroanimator.catalog.tasks import TASKS
from neuroanimator.contracts.controller import TaskInfo, TaskList
from services.controller.store import clean

router = APIRouter(tags=["tasks"])


@router.get("/tasks", response_model=TaskList)
def list_tasks() -> TaskList:
    """The built-in tasks (thesis section 6.2): model, start and target states, objective, optimizer."""
    return TaskList(tasks=[TaskInfo(**clean(t.to_dict())) for t in TASKS.values()])
