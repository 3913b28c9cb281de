"""Wire format and typed messages (msgpack, no pickle), validated on receipt.

`wire` holds the envelope, numpy arrays and the field checks; `data` the transition batches and
weights; `control` allocation, evaluation and done; `stats` the learner's counters. Callers use
`from services.messaging.codec import ...`. This package must not import zenoh.
"""

from services.messaging.codec.control import Allocation, Done, Eval
from services.messaging.codec.data import SlotEpisode, TransitionBatch, TransitionSpec, Weights
from services.messaging.codec.stats import LearnerStats, WorkerCounters
from services.messaging.codec.wire import (
                                 DTYPES,
                                 HEADER_KEYS,
                                 MAX_ARRAY_LEN,
                                 MAX_DIM,
                                 MAX_MAP_LEN,
                                 MAX_MESSAGE_BYTES,
                                 MAX_NDIM,
                                 MAX_STR_LEN,
                                 MAX_TEXT_LEN,
                                 NDARRAY_EXT,
                                 SCHEMA_VERSION,
                                 MessageError,
                                 decode,
                                 encode,
                                 pack_default,
                                 unpack_ext_hook,
)

__all__ = ["DTYPES", "HEADER_KEYS", "MAX_ARRAY_LEN", "MAX_DIM", "MAX_MAP_LEN", "MAX_MESSAGE_BYTES", "MAX_NDIM",
           "MAX_STR_LEN", "MAX_TEXT_LEN", "NDARRAY_EXT", "SCHEMA_VERSION", "Allocation", "Done", "Eval",
           "LearnerStats", "MessageError", "SlotEpisode", "TransitionBatch", "TransitionSpec", "Weights",
           "WorkerCounters", "pack_default", "unpack_ext_hook", "decode", "encode"]
