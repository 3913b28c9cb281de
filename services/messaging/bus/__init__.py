"""Opening Zenoh sessions and the few pub/sub pieces every role uses.

This package is the only one (with the services that call it) that imports zenoh. Its modules:
`session` (configs, sessions, publishers), `receive` (Inbox, Latest), `alive` (liveliness) and
`accounting` (sequence numbers, rejections; no zenoh), `query` (a queryable answered from a
role's loop, and asking). Callers use `from services.messaging import bus`.

Topology: a star. The learner (or a ``mode: router`` session) listens; workers, the
referee and monitors connect to it as clients. On one box the launcher picks a free
port and uses ``tcp/127.0.0.1:<port>``, admitting only sessions that present the run's
secret (``AUTH_ENV``, user-password authentication; services/run/secret.py). Multicast and
gossip scouting are off unless a config file turns them on, so processes only meet through
explicit endpoints.

Delivery rules (docs/ZENOH-NOTES.md has the measurements behind them):

* everything is published RELIABLE with CongestionControl.BLOCK (``put`` defaults to
  DROP and lost 5-90% under load);
* "latest value" topics (weights, allocation) use Zenoh's advanced publisher with a
  one-sample cache per key, and subscribers ask for that history when they start or when
  they discover a publisher: a late joiner gets the current value at once
  (``declare_latest_publisher`` / ``Latest.subscribe``);
* subscriber callbacks run on Zenoh's receive thread: they only copy the payload into a
  Python structure (``Inbox`` or ``Latest``) and return; the service loop does the work.

Traps met while building this (zenoh 1.10.2; more in docs/ZENOH-NOTES.md):

* the advanced publisher refuses to start unless ``timestamping/enabled`` is true;
* with its default per-session timestamp ordering, a wildcard late joiner
  (``weights/*``) silently lost one actor's cached weights when the learner's session
  held two publishers: we turn on per-publisher sequence numbers instead;
* a liveliness token whose Python object is dropped is undeclared at once;
* a subscriber callback that waits on every sample of a stalled consumer stalls the
  link until the publisher's BLOCK gives up and the transport closes (see ``Inbox``).
"""

from services.messaging.bus.accounting import (
                                     DUPLICATE,
                                     GAP,
                                     IN_ORDER,
                                     MAX_HOLES,
                                     RECOVERED,
                                     REDUNDANT,
                                     RejectLog,
                                     SequenceTracker,
                                     run_is_done,
)
from services.messaging.bus.alive import AliveWatch, declare_alive, watch_alive
from services.messaging.bus.query import Answers, ask, ask_all
from services.messaging.bus.receive import Inbox, Latest, Received
from services.messaging.bus.session import (
                                     AUTH_ENV,
                                     MODES,
                                     REFUSALS_LOG,
                                     declare_latest_publisher,
                                     declare_reliable_publisher,
                                     free_tcp_port,
                                     init_zenoh_log,
                                     loopback_endpoint,
                                     make_config,
                                     open_session,
                                     refused,
                                     session_scope,
                                     use_credentials,
)

__all__ = ["AUTH_ENV", "DUPLICATE", "GAP", "IN_ORDER", "MAX_HOLES", "MODES", "RECOVERED", "REDUNDANT", "REFUSALS_LOG",
           "AliveWatch", "Answers", "Inbox", "Latest", "Received", "RejectLog", "SequenceTracker", "ask", "ask_all",
           "declare_alive", "declare_latest_publisher", "declare_reliable_publisher", "free_tcp_port", "init_zenoh_log",
           "loopback_endpoint", "make_config", "open_session", "refused", "run_is_done", "session_scope",
           "use_credentials",
           "watch_alive"]
