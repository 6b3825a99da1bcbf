"""The one module a service kind calls: everything the core offers kinds, by name.

A kind (``kinds/<name>/``) imports this module and models (``services.models``,
``fleet.models``, ``accounts.users``) and nothing else of the core: import-linter's
"kinds-use-the-kit" contract keeps it so. What is here is the core's promise to kinds;
what is not, a kind does not rely on, so the core can move its insides freely. See
docs/writing-a-service.md for how each is used.

* **Declare** the kind: :class:`ServiceKind` and the registry's :func:`kind_register`;
  :class:`Request`, :class:`Opened`, :class:`RequestError`, :class:`DemoService`.
* **Open** a session (the one route, for every kind): :func:`session_open`; it raises
  :class:`AssignmentError` or :class:`DeploymentError`.
* **Step** an autonomous workflow: find and reserve vehicles (:func:`role_assign`,
  :func:`role_capable`, :func:`trip_m`), send them their task (:func:`vehicle_task_deploy`),
  watch them (:func:`vehicle_trouble`, :func:`vehicles_unfit`), let one go
  (:func:`assignment_release`), move the session on (:func:`session_transition`,
  :func:`session_task_accepted`, :func:`workflow_state_set`), run the timer's pass
  (:func:`steps_run`, :func:`task_redeploy_if_unaccepted`).
* **End** it: :func:`session_close` (the vehicles are told and released).
* **Log**: :func:`event_append` (the session's hash-chained log, pushed live).
* **Notify** people outside the session: :func:`notice_create`.
* **Present** it: :func:`session_watched` (who may see a session's page),
  :func:`log_lines`, :func:`session_vehicle_names`, :func:`session_summary`,
  :func:`session_situation`, :func:`session_consequence`, :func:`waiting_words`,
  :func:`reach_map`, :func:`km`, a viewer's grant (:func:`grant_issue`,
  :func:`user_task_json`, :func:`user_can_use`) and the rate limit on pages that mint
  one (:func:`throttled`).
* **Vehicles' declarations**: the camera vocabulary (:data:`CAMERAS`), the features
  (:data:`FEATURES`), a vehicle's declared camera optics (:func:`camera_optics`, a
  :class:`CameraOptics`: field of view, picture size, footprint at an altitude).
* **Demo world**: the vocabularies and places the demo's vehicles and services use.
"""

from __future__ import annotations

from fleet.attributes import CAMERAS, FEATURES, CameraOptics, camera_optics
from services.demo import (
    BOAT_COMMANDS,
    CAR_COMMANDS,
    CASTAWAY,
    COSTA_NOVA,
    QUADCOPTER_COMMANDS,
    VTOL_COMMANDS,
    command_names,
)
from services.kinds import (
    DemoService,
    EventHandler,
    Opened,
    Request,
    RequestError,
    ServiceKind,
    kind_register,
)
from services.sessions.deployment import (
    DeploymentError,
    grant_issue,
    user_task_json,
    vehicle_task_deploy,
)
from services.sessions.feasibility import Reach, km, reach_map, role_capable, trip_m, waiting_words
from services.sessions.grants import user_can_use
from services.sessions.log import event_append
from services.sessions.matching import AssignmentError, role_assign
from services.sessions.notices import notice_create
from services.sessions.opening import session_open
from services.sessions.selectors import session_consequence, session_summary
from services.sessions.states import FINAL, session_transition
from services.sessions.workflow import (
    assignment_release,
    session_close,
    session_task_accepted,
    steps_run,
    task_redeploy_if_unaccepted,
    vehicle_trouble,
    vehicles_unfit,
    workflow_state_set,
)
from services.supervision.situation import session_situation
from services.web.throttle import throttled
from services.web.watching import log_lines, session_vehicle_names, session_watched

# Grouped by use in the module's docstring.
__all__ = [
    "BOAT_COMMANDS",
    "CAMERAS",
    "CAR_COMMANDS",
    "CASTAWAY",
    "COSTA_NOVA",
    "FEATURES",
    "FINAL",
    "QUADCOPTER_COMMANDS",
    "VTOL_COMMANDS",
    "AssignmentError",
    "CameraOptics",
    "DemoService",
    "DeploymentError",
    "EventHandler",
    "Opened",
    "Reach",
    "Request",
    "RequestError",
    "ServiceKind",
    "assignment_release",
    "camera_optics",
    "command_names",
    "event_append",
    "grant_issue",
    "kind_register",
    "km",
    "log_lines",
    "notice_create",
    "reach_map",
    "role_assign",
    "role_capable",
    "session_close",
    "session_consequence",
    "session_open",
    "session_situation",
    "session_summary",
    "session_task_accepted",
    "session_transition",
    "session_vehicle_names",
    "session_watched",
    "steps_run",
    "task_redeploy_if_unaccepted",
    "throttled",
    "trip_m",
    "user_can_use",
    "user_task_json",
    "vehicle_task_deploy",
    "vehicle_trouble",
    "vehicles_unfit",
    "waiting_words",
    "workflow_state_set",
]
