/* The serial link's own thread (see link.py): what klippy's serialqueue.c does for its host,
 * here for ours. The thread owns the device's reads: it stamps each block with its arrival
 * time, acknowledges what was sent, resends on a nak or a retransmission timeout, refills the
 * window from the queued messages as acknowledgements free it, and keeps the blocks that carry
 * responses for the Python side, which takes them when it looks (its ticks) or when this
 * thread signals an eventfd (only when asked to, and for a fault). So the Python side wakes for
 * its own ticks, not for the link's bookkeeping: a wake of the interpreter costs far more than
 * one of this thread.
 *
 * The sequence window follows Klipper's protocol (docs/Protocol.md): 4-bit sequence numbers,
 * the MCU's receive window in bytes, acknowledgements in empty blocks and in responses, a nak
 * repeating the number of the last empty block. The rules are those the window's tests
 * (tests/unit/test_klipper_serialq.py) hold: naks ignored for two round trips after a resend,
 * the retransmission timeout doubled on each timeout and reset by a fresh measurement, a
 * sequence number never sent a restart, except before the first acknowledgement (an MCU that
 * served a host before keeps its count, which is adopted, once a timeout at most).
 *
 * Locking: one mutex guards the state; the Python side takes it (holding the GIL) for short
 * calls, the thread takes it but never the GIL, so neither waits for the other long. */
#include "_serialq.h"

int stepcore_add_type(PyObject *module, PyTypeObject *type, const char *name); /* _stepcore.c */

/* -- the Python side -------------------------------------------------------------------- */
/* After a call changed what the thread waits for: wake it if it would wait too long. */
static void wake_if_needed(SerialQueue *s)
{
    if (deadline_s(s) < s->thread_deadline_s || s->out_len) {
        s->thread_deadline_s = -INFINITY; /* once: the thread sets it again */
        kick(s->wake_fd);
    }
}

static int queue_message(SerialQueue *s, PyObject *item, int keep)
{
    char *data;
    Py_ssize_t len;
    if (PyBytes_AsStringAndSize(item, &data, &len) < 0)
        return -1;
    if (len < 1 || len > PAYLOAD_MAX) {
        PyErr_Format(PyExc_ValueError, "a message of %zd bytes (1 to %d)", len, PAYLOAD_MAX);
        return -1;
    }
    if (s->queue_len == s->queue_cap) {
        struct message *grown = ring_grow(s->queue, sizeof *s->queue, &s->queue_cap,
                                          &s->queue_head);
        if (grown == NULL) {
            PyErr_NoMemory();
            return -1;
        }
        s->queue = grown;
    }
    struct message *m = &s->queue[(s->queue_head + s->queue_len++) % s->queue_cap];
    m->len = (uint8_t)len;
    m->keep = (uint8_t)keep;
    memcpy(m->data, data, (size_t)len);
    s->queue_bytes += (size_t)len;
    return 0;
}

static const char send_doc[] =
"send(messages, keep=False, keep_first=0)\n\n"
"Queue encoded messages (each at most 59 bytes) and send what the window has room for now, as\n"
"many to a block as fit; ``keep``: none is dropped by send_first (requests), as the first\n"
"``keep_first`` never are.";

static PyObject *sq_send(SerialQueue *s, PyObject *args, PyObject *kwargs)
{
    static char *names[] = {"messages", "keep", "keep_first", NULL};
    PyObject *messages;
    int keep = 0;
    Py_ssize_t keep_first = 0;
    if (!PyArg_ParseTupleAndKeywords(args, kwargs, "O|pn", names, &messages, &keep,
                                     &keep_first))
        return NULL;
    PyObject *seq = PySequence_Fast(messages, "messages must be a sequence of bytes");
    if (seq == NULL)
        return NULL;
    Py_ssize_t count = PySequence_Fast_GET_SIZE(seq);
    PyObject **items = PySequence_Fast_ITEMS(seq);
    int failed = 0;
    pthread_mutex_lock(&s->lock);
    if (!s->dead) {
        for (Py_ssize_t i = 0; i < count && !failed; i++)
            failed = queue_message(s, items[i], keep || i < keep_first) < 0;
        pump(s, now_s());
        wake_if_needed(s);
    }
    pthread_mutex_unlock(&s->lock);
    Py_DECREF(seq);
    if (failed)
        return NULL;
    Py_RETURN_NONE;
}

static const char send_first_doc[] =
"send_first(message) -> list[bytes]\n\n"
"Send ``message`` now in a block of its own, whatever room the window has, before everything\n"
"queued; what was queued and not kept is dropped and returned.";

static PyObject *sq_send_first(SerialQueue *s, PyObject *arg)
{
    char *data;
    Py_ssize_t len;
    if (PyBytes_AsStringAndSize(arg, &data, &len) < 0)
        return NULL;
    if (len < 1 || len > PAYLOAD_MAX) {
        PyErr_Format(PyExc_ValueError, "a message of %zd bytes (1 to %d)", len, PAYLOAD_MAX);
        return NULL;
    }
    PyObject *dropped = PyList_New(0);
    if (dropped == NULL)
        return NULL;
    pthread_mutex_lock(&s->lock);
    if (s->inflight_len == MAX_BLOCKS) { /* (the window fills 12: three send_first past it) */
        pthread_mutex_unlock(&s->lock);
        Py_DECREF(dropped);
        PyErr_Format(PyExc_BufferError, "%d blocks unacknowledged: no room for another",
                     MAX_BLOCKS);
        return NULL;
    }
    size_t kept = 0;
    for (size_t i = 0; i < s->queue_len; i++) {
        struct message m = s->queue[(s->queue_head + i) % s->queue_cap];
        if (m.keep) {
            s->queue[(s->queue_head + kept++) % s->queue_cap] = m;
            continue;
        }
        s->queue_bytes -= m.len;
        PyObject *b = PyBytes_FromStringAndSize((const char *)m.data, m.len);
        if (b == NULL || PyList_Append(dropped, b) < 0) {
            Py_XDECREF(b);
            Py_DECREF(dropped);
            dropped = NULL;
            break;
        }
        Py_DECREF(b);
    }
    if (dropped != NULL) {
        s->queue_len = kept;
        if (!s->dead) {
            double now = now_s();
            new_block(s, (const uint8_t *)data, (int)len, now);
            pump(s, now);
            wake_if_needed(s);
        }
    }
    pthread_mutex_unlock(&s->lock);
    return dropped;
}

static const char pull_doc[] =
"pull(limit_bytes) -> (blocks, fault, more)\n\n"
"The responses' payloads received since the last pull, each with its arrival time\n"
"(time.monotonic), up to about ``limit_bytes`` of them; the fault that ended the link, once\n"
"(None, or (kind, text): kind 'broken' (nothing more is read, writing still works), 'read',\n"
"'write' or 'hangup'); whether more blocks wait.";

static PyObject *sq_pull(SerialQueue *s, PyObject *arg)
{
    Py_ssize_t limit = PyLong_AsSsize_t(arg);
    if (limit == -1 && PyErr_Occurred())
        return NULL;
    PyObject *blocks = PyList_New(0);
    if (blocks == NULL)
        return NULL;
    pthread_mutex_lock(&s->lock);
    int resume = s->rx_len >= RX_LIMIT;
    Py_ssize_t taken = 0;
    while (s->rx_len && taken < limit) {
        struct received *r = &s->rx[s->rx_head];
        PyObject *item = Py_BuildValue("(y#d)", r->data, (Py_ssize_t)r->len, r->received_s);
        if (item == NULL || PyList_Append(blocks, item) < 0) {
            Py_XDECREF(item);
            pthread_mutex_unlock(&s->lock);
            Py_DECREF(blocks);
            return NULL;
        }
        Py_DECREF(item);
        taken += r->len;
        s->rx_head = (s->rx_head + 1) % s->rx_cap;
        s->rx_len--;
    }
    int more = s->rx_len > 0;
    if (s->notified) { /* the signal is taken with what it announced */
        uint64_t count;
        ssize_t r = read(s->notify_fd, &count, sizeof count);
        (void)r;
        s->notified = 0;
    }
    PyObject *fault = Py_None;
    Py_INCREF(fault);
    if (s->fault != NONE && !s->fault_taken && !more) {
        static const char *kinds[] = {"", "broken", "read", "write", "hangup"};
        Py_DECREF(fault);
        fault = Py_BuildValue("(ss)", kinds[s->fault], s->fault_text);
        s->fault_taken = 1;
    }
    if (resume && s->rx_len < RX_LIMIT)
        kick(s->wake_fd);
    pthread_mutex_unlock(&s->lock);
    if (fault == NULL) {
        Py_DECREF(blocks);
        return NULL;
    }
    return Py_BuildValue("(NNO)", blocks, fault, more ? Py_True : Py_False);
}

static const char set_notify_doc[] =
"set_notify(on)\n\n"
"Whether each response's arrival is signalled on ``notify_fd`` (a fault always is); turned on\n"
"with responses waiting, it signals at once.";

static PyObject *sq_set_notify(SerialQueue *s, PyObject *arg)
{
    int on = PyObject_IsTrue(arg);
    if (on < 0)
        return NULL;
    pthread_mutex_lock(&s->lock);
    s->notify = on;
    if (on && s->rx_len && !s->notified) {
        s->notified = 1;
        s->signals++;
        kick(s->notify_fd);
    }
    pthread_mutex_unlock(&s->lock);
    Py_RETURN_NONE;
}

static const char halt_doc[] =
"halt(text)\n\n"
"Stop reading and judging (the Python side found the stream broken: a message it cannot\n"
"decode); writing still works. The fault is this one if none came before.";

static PyObject *sq_halt(SerialQueue *s, PyObject *arg)
{
    const char *text = PyUnicode_AsUTF8(arg);
    if (text == NULL)
        return NULL;
    pthread_mutex_lock(&s->lock);
    if (s->fault == NONE) {
        s->fault = BROKEN;
        snprintf(s->fault_text, sizeof s->fault_text, "%s", text);
        s->fault_taken = 1; /* the Python side knows: nothing to signal */
    }
    if (s->notified) { /* nothing more is taken: a pending signal is dropped */
        uint64_t count;
        ssize_t r = read(s->notify_fd, &count, sizeof count);
        (void)r;
        s->notified = 0;
    }
    s->failed = 1;
    kick(s->wake_fd);
    pthread_mutex_unlock(&s->lock);
    Py_RETURN_NONE;
}

static void stop_thread(SerialQueue *s)
{
    if (!s->started)
        return;
    pthread_mutex_lock(&s->lock);
    s->closing = 1;
    kick(s->wake_fd);
    pthread_mutex_unlock(&s->lock);
    Py_BEGIN_ALLOW_THREADS
    pthread_join(s->thread, NULL);
    Py_END_ALLOW_THREADS
    s->started = 0;
}

static const char close_doc[] =
"close()\n\nEnd the thread (the device is the caller's to close); safe twice.";

static PyObject *sq_close(SerialQueue *s, PyObject *unused)
{
    (void)unused;
    stop_thread(s);
    pthread_mutex_lock(&s->lock);
    s->dead = s->failed = 1;
    pthread_mutex_unlock(&s->lock);
    Py_RETURN_NONE;
}

/* ``data`` appended to ``*list`` as bytes; on failure the list is released (NULL). */
static void append_bytes(PyObject **list, const uint8_t *data, size_t len)
{
    PyObject *b = PyBytes_FromStringAndSize((const char *)data, (Py_ssize_t)len);
    if (b == NULL || PyList_Append(*list, b) < 0)
        Py_CLEAR(*list);
    Py_XDECREF(b);
}

static const char inflight_doc[] =
"inflight() -> list[bytes]\n\nThe payloads of the blocks not yet acknowledged, oldest first.";

static PyObject *sq_inflight(SerialQueue *s, PyObject *unused)
{
    (void)unused;
    PyObject *list = PyList_New(0);
    if (list == NULL)
        return NULL;
    pthread_mutex_lock(&s->lock);
    for (int i = 0; i < s->inflight_len && list != NULL; i++) {
        struct sent *sent = inflight_at(s, i);
        append_bytes(&list, sent->block + 2, sent->payload_len);
    }
    pthread_mutex_unlock(&s->lock);
    return list;
}

static const char queued_doc[] =
"queued() -> list[bytes]\n\nThe messages waiting for room in the window, in order.";

static PyObject *sq_queued(SerialQueue *s, PyObject *unused)
{
    (void)unused;
    PyObject *list = PyList_New(0);
    if (list == NULL)
        return NULL;
    pthread_mutex_lock(&s->lock);
    for (size_t i = 0; i < s->queue_len && list != NULL; i++) {
        struct message *m = &s->queue[(s->queue_head + i) % s->queue_cap];
        append_bytes(&list, m->data, m->len);
    }
    pthread_mutex_unlock(&s->lock);
    return list;
}

static const char stats_doc[] =
"stats() -> dict\n\n"
"The link's counts and state: bytes_sent, bytes_received, queued_bytes, inflight (blocks),\n"
"inflight_bytes, next_seq, acked, retransmits, srtt_s (None before a measurement), rto_s,\n"
"bad_blocks, wakes (of the thread), signals (on notify_fd), writes (to the device).";

static PyObject *sq_stats(SerialQueue *s, PyObject *unused)
{
    (void)unused;
    pthread_mutex_lock(&s->lock);
    PyObject *srtt = s->srtt_s < 0 ? Py_None : PyFloat_FromDouble(s->srtt_s);
    PyObject *d = Py_BuildValue(
        "{sKsKsnsisisKsKslsOsdslsKsKsK}",
        "bytes_sent", s->bytes_sent, "bytes_received", s->bytes_received,
        "queued_bytes", (Py_ssize_t)s->queue_bytes, "inflight", s->inflight_len,
        "inflight_bytes", s->bytes_in_flight,
        "next_seq", (unsigned long long)s->next_seq, "acked", (unsigned long long)s->acked,
        "retransmits", s->retransmits, "srtt_s", srtt, "rto_s", s->rto_s,
        "bad_blocks", s->bad_blocks, "wakes", s->wakes, "signals", s->signals,
        "writes", s->writes);
    if (srtt != Py_None)
        Py_XDECREF(srtt);
    pthread_mutex_unlock(&s->lock);
    return d;
}

static PyObject *get_queued_bytes(SerialQueue *s, void *closure)
{
    (void)closure;
    pthread_mutex_lock(&s->lock);
    size_t queued = s->queue_bytes;
    pthread_mutex_unlock(&s->lock);
    return PyLong_FromSize_t(queued);
}

static PyObject *get_in_flight(SerialQueue *s, void *closure)
{
    (void)closure;
    pthread_mutex_lock(&s->lock);
    int count = s->inflight_len;
    pthread_mutex_unlock(&s->lock);
    return PyLong_FromLong(count);
}

static PyObject *get_bytes(SerialQueue *s, void *closure)
{
    pthread_mutex_lock(&s->lock);
    unsigned long long count = closure ? s->bytes_received : s->bytes_sent;
    pthread_mutex_unlock(&s->lock);
    return PyLong_FromUnsignedLongLong(count);
}

static PyObject *get_notify_fd(SerialQueue *s, void *closure)
{
    (void)closure;
    return PyLong_FromLong(s->notify_fd);
}

static int set_double(SerialQueue *s, PyObject *value, double *field, double none)
{
    double v = none;
    if (value == NULL) {
        PyErr_SetString(PyExc_AttributeError, "cannot delete");
        return -1;
    }
    if (value != Py_None) {
        v = PyFloat_AsDouble(value);
        if (v == -1.0 && PyErr_Occurred())
            return -1;
    }
    pthread_mutex_lock(&s->lock);
    *field = v;
    wake_if_needed(s);
    pthread_mutex_unlock(&s->lock);
    return 0;
}

static PyObject *get_ack_timeout(SerialQueue *s, void *closure)
{
    (void)closure;
    if (s->ack_timeout_s < 0)
        Py_RETURN_NONE;
    return PyFloat_FromDouble(s->ack_timeout_s);
}

static int set_ack_timeout(SerialQueue *s, PyObject *value, void *closure)
{
    (void)closure;
    return set_double(s, value, &s->ack_timeout_s, -1.0);
}

static PyObject *get_window_bytes(SerialQueue *s, void *closure)
{
    (void)closure;
    return PyLong_FromLong(s->window_bytes);
}

static int set_window_bytes(SerialQueue *s, PyObject *value, void *closure)
{
    (void)closure;
    long v = value == NULL ? -1 : PyLong_AsLong(value);
    if (v == -1 && (value == NULL || PyErr_Occurred())) {
        if (!PyErr_Occurred())
            PyErr_SetString(PyExc_AttributeError, "cannot delete");
        return -1;
    }
    if (v < MESSAGE_MAX) {
        PyErr_Format(PyExc_ValueError, "a window of %ld bytes (a block needs %d)", v,
                     MESSAGE_MAX);
        return -1;
    }
    pthread_mutex_lock(&s->lock);
    s->window_bytes = (int)v;
    pump(s, now_s());
    wake_if_needed(s);
    pthread_mutex_unlock(&s->lock);
    return 0;
}

static int sq_init(SerialQueue *s, PyObject *args, PyObject *kwargs)
{
    static char *names[] = {"fd", "window_bytes", "max_blocks", NULL};
    int fd, window_bytes = 192, max_blocks = 12;
    if (!PyArg_ParseTupleAndKeywords(args, kwargs, "i|ii", names, &fd, &window_bytes,
                                     &max_blocks))
        return -1;
    if (s->started) {
        PyErr_SetString(PyExc_RuntimeError, "already running");
        return -1;
    }
    if (max_blocks < 1 || max_blocks > WINDOW_BLOCKS || window_bytes < MESSAGE_MAX) {
        PyErr_Format(PyExc_ValueError, "max_blocks 1 to %d, window_bytes %d at least",
                     WINDOW_BLOCKS, MESSAGE_MAX);
        return -1;
    }
    s->fd = fd;
    s->window_bytes = window_bytes;
    s->max_blocks = max_blocks;
    s->rto_s = MIN_RTO_S * 4;
    s->srtt_s = -1.0;
    s->ack_timeout_s = -1.0;
    s->thread_deadline_s = INFINITY;
    s->wake_fd = eventfd(0, EFD_NONBLOCK | EFD_CLOEXEC);
    s->notify_fd = eventfd(0, EFD_NONBLOCK | EFD_CLOEXEC);
    if (s->wake_fd < 0 || s->notify_fd < 0) {
        PyErr_SetFromErrno(PyExc_OSError);
        return -1;
    }
    int error = pthread_create(&s->thread, NULL, run, s);
    if (error) {
        errno = error;
        PyErr_SetFromErrno(PyExc_OSError);
        return -1;
    }
    s->started = 1;
    return 0;
}

static PyObject *sq_new(PyTypeObject *type, PyObject *args, PyObject *kwargs)
{
    (void)args;
    (void)kwargs;
    SerialQueue *s = (SerialQueue *)type->tp_alloc(type, 0);
    if (s == NULL)
        return NULL;
    pthread_mutex_init(&s->lock, NULL);
    s->fd = s->wake_fd = s->notify_fd = -1;
    return (PyObject *)s;
}

static void sq_dealloc(SerialQueue *s)
{
    stop_thread(s);
    if (s->wake_fd >= 0)
        close(s->wake_fd);
    if (s->notify_fd >= 0)
        close(s->notify_fd);
    PyMem_RawFree(s->queue);
    PyMem_RawFree(s->rx);
    free(s->out);
    pthread_mutex_destroy(&s->lock);
    Py_TYPE(s)->tp_free((PyObject *)s);
}

static PyMethodDef sq_methods[] = {
    {"send", (PyCFunction)(void (*)(void))sq_send, METH_VARARGS | METH_KEYWORDS, send_doc},
    {"send_first", (PyCFunction)sq_send_first, METH_O, send_first_doc},
    {"pull", (PyCFunction)sq_pull, METH_O, pull_doc},
    {"set_notify", (PyCFunction)sq_set_notify, METH_O, set_notify_doc},
    {"halt", (PyCFunction)sq_halt, METH_O, halt_doc},
    {"close", (PyCFunction)sq_close, METH_NOARGS, close_doc},
    {"inflight", (PyCFunction)sq_inflight, METH_NOARGS, inflight_doc},
    {"queued", (PyCFunction)sq_queued, METH_NOARGS, queued_doc},
    {"stats", (PyCFunction)sq_stats, METH_NOARGS, stats_doc},
    {NULL, NULL, 0, NULL},
};

static PyGetSetDef sq_getset[] = {
    {"queued_bytes", (getter)get_queued_bytes, NULL, "message bytes waiting for room", NULL},
    {"in_flight", (getter)get_in_flight, NULL, "blocks not yet acknowledged", NULL},
    {"bytes_sent", (getter)get_bytes, NULL, "bytes written (framing and resends too)", NULL},
    {"bytes_received", (getter)get_bytes, NULL, "bytes read", (void *)1},
    {"notify_fd", (getter)get_notify_fd, NULL, "the eventfd a response or fault signals", NULL},
    {"ack_timeout_s", (getter)get_ack_timeout, (setter)set_ack_timeout,
     "a block unacknowledged this long is a fault (None: no limit)", NULL},
    {"window_bytes", (getter)get_window_bytes, (setter)set_window_bytes,
     "the MCU's receive window", NULL},
    {NULL, NULL, NULL, NULL, NULL},
};

static PyTypeObject SerialQueueType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "server.backends.klipper._stepcore.SerialQueue",
    .tp_basicsize = sizeof(SerialQueue),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = "SerialQueue(fd, window_bytes=192, max_blocks=12)\n\n"
              "A thread owning a Klipper MCU link's reads, acknowledgements and resends (see\n"
              "_serialq.c).",
    .tp_new = sq_new,
    .tp_init = (initproc)sq_init,
    .tp_dealloc = (destructor)sq_dealloc,
    .tp_methods = sq_methods,
    .tp_getset = sq_getset,
};

int serialq_add_type(PyObject *module)
{
    return stepcore_add_type(module, &SerialQueueType, "SerialQueue");
}
