/* The MCU's move queue seen from the host, compiled (movequeue.py explains it and wraps it):
 * the messages waiting to be sent, each with the move-queue slot it takes until its clock has
 * passed (or none) and when it is due, and a heap of the clocks the taken slots free at. One
 * call a sample (pump) finds what leaves in one burst; as klippy's steppersync keeps its
 * move-queue count in C. */
#include "_stepcore.h"
#include <math.h>
#include <string.h>

#define NO_SLOT INT64_MIN
#define LATE_MARGIN_S 0.002
#define QUEUE_MARGIN_S 0.001

typedef struct {
    PyObject *message; /* bytes */
    int64_t until;     /* the clock its slot frees at; NO_SLOT: it takes none */
    int64_t due;
} Entry;

typedef struct {
    PyObject_HEAD
    Entry *ring;       /* the waiting messages: ring[(head + i) % cap] */
    Py_ssize_t head, len, cap;
    int64_t *heap;     /* the taken slots' clocks, a min-heap */
    Py_ssize_t used, heap_cap;
    Py_ssize_t payload_max; /* a message block's payload (codec.PAYLOAD_MAX) */
} MoveQueue;

static Entry *at(MoveQueue *q, Py_ssize_t i)
{
    return &q->ring[(q->head + i) % q->cap];
}

static int push(MoveQueue *q, PyObject *message, PyObject *until, long long due)
{
    if (!PyBytes_Check(message)) {
        PyErr_SetString(PyExc_TypeError, "a message is bytes");
        return -1;
    }
    int64_t slot = NO_SLOT;
    if (until != Py_None) {
        slot = PyLong_AsLongLong(until);
        if (slot == -1 && PyErr_Occurred())
            return -1;
    }
    if (q->len == q->cap) {
        Py_ssize_t cap = q->cap ? 2 * q->cap : 64;
        Entry *ring = PyMem_Malloc((size_t)cap * sizeof(Entry));
        if (ring == NULL) {
            PyErr_NoMemory();
            return -1;
        }
        for (Py_ssize_t i = 0; i < q->len; i++)
            ring[i] = *at(q, i);
        PyMem_Free(q->ring);
        q->ring = ring;
        q->head = 0;
        q->cap = cap;
    }
    Py_INCREF(message);
    *at(q, q->len++) = (Entry){message, slot, due};
    return 0;
}

static void pop_front(MoveQueue *q)
{
    Py_DECREF(at(q, 0)->message);
    q->head = (q->head + 1) % q->cap;
    q->len--;
}

static int heap_push(MoveQueue *q, int64_t clock)
{
    if (q->used == q->heap_cap) {
        Py_ssize_t cap = q->heap_cap ? 2 * q->heap_cap : 64;
        int64_t *heap = PyMem_Realloc(q->heap, (size_t)cap * sizeof(int64_t));
        if (heap == NULL) {
            PyErr_NoMemory();
            return -1;
        }
        q->heap = heap;
        q->heap_cap = cap;
    }
    Py_ssize_t i = q->used++;
    while (i && q->heap[(i - 1) / 2] > clock) {
        q->heap[i] = q->heap[(i - 1) / 2];
        i = (i - 1) / 2;
    }
    q->heap[i] = clock;
    return 0;
}

static void heap_pop(MoveQueue *q)
{
    int64_t last = q->heap[--q->used];
    Py_ssize_t i = 0;
    for (;;) {
        Py_ssize_t child = 2 * i + 1;
        if (child >= q->used)
            break;
        if (child + 1 < q->used && q->heap[child + 1] < q->heap[child])
            child++;
        if (q->heap[child] >= last)
            break;
        q->heap[i] = q->heap[child];
        i = child;
    }
    if (q->used)
        q->heap[i] = last;
}

PyDoc_STRVAR(add_doc,
"add(message, until, due)\n\n"
"Queue message; until is the MCU clock its slot frees at (None: it takes no slot).");

static PyObject *mq_add(MoveQueue *q, PyObject *args)
{
    PyObject *message, *until;
    long long due;
    if (!PyArg_ParseTuple(args, "OOL", &message, &until, &due) || push(q, message, until, due) < 0)
        return NULL;
    Py_RETURN_NONE;
}

PyDoc_STRVAR(extend_doc, "extend(triples)\n\nQueue (message, until, due) triples, as add.");

static PyObject *mq_extend(MoveQueue *q, PyObject *triples)
{
    if (!PyList_Check(triples)) {
        PyErr_SetString(PyExc_TypeError, "a list of (message, until, due) triples");
        return NULL;
    }
    for (Py_ssize_t i = 0; i < PyList_GET_SIZE(triples); i++) {
        PyObject *t = PyList_GET_ITEM(triples, i), *message, *until;
        long long due;
        if (!PyTuple_Check(t) || !PyArg_ParseTuple(t, "OOL", &message, &until, &due)
            || push(q, message, until, due) < 0)
            return NULL;
    }
    Py_RETURN_NONE;
}

/* How many waiting messages go now: all if the last block they fill (packed in order, as the
 * link does) has one due by hold_after, else those of the blocks before it. */
static Py_ssize_t ready(MoveQueue *q, double hold_after)
{
    Py_ssize_t count = 0, fill = 0;
    int due_soon = 0;
    for (Py_ssize_t i = 0; i < q->len; i++) {
        Entry *e = at(q, i);
        Py_ssize_t size = PyBytes_GET_SIZE(e->message);
        if (fill + size > q->payload_max) { /* the block before is full: it goes */
            count = i;
            fill = 0;
            due_soon = 0;
        }
        fill += size;
        due_soon = due_soon || (double)e->due <= hold_after;
    }
    return due_soon ? q->len : count;
}

PyDoc_STRVAR(pump_doc,
"pump(move_count, now, freq, hold_after) -> (burst, late_ms)\n\n"
"What leaves now at MCU clock now, in order, while the move queue (move_count slots) has\n"
"room: a list of messages (None: nothing), and how many ms late the next message would be\n"
"(nothing more goes: the caller halts), or None. hold_after: an MCU clock, or None; the\n"
"messages of a last block not filled wait while none of them is due by it.");

static PyObject *mq_pump(MoveQueue *q, PyObject *args)
{
    Py_ssize_t move_count;
    double now, freq;
    PyObject *hold_obj;
    if (!PyArg_ParseTuple(args, "nddO", &move_count, &now, &freq, &hold_obj))
        return NULL;
    double freed = now - QUEUE_MARGIN_S * freq; /* slots freed count free (see turn) */
    while (q->used && (double)q->heap[0] <= freed)
        heap_pop(q);
    Py_ssize_t count = q->len;
    if (hold_obj != Py_None) {
        double hold_after = PyFloat_AsDouble(hold_obj);
        if (hold_after == -1.0 && PyErr_Occurred())
            return NULL;
        count = ready(q, hold_after);
    }
    if (!count)
        return Py_BuildValue("(OO)", Py_None, Py_None);
    double late = now + LATE_MARGIN_S * freq;
    PyObject *burst = PyList_New(0), *late_ms = Py_None;
    if (burst == NULL)
        return NULL;
    Py_INCREF(late_ms);
    while (q->len && PyList_GET_SIZE(burst) < count) {
        Entry *e = at(q, 0);
        if (e->until != NO_SLOT) {
            if (q->used >= move_count)
                break;
            if ((double)e->due < late) {
                Py_DECREF(late_ms);
                late_ms = PyFloat_FromDouble(freq ? (late - (double)e->due) / freq * 1e3 : 0.0);
                if (late_ms == NULL)
                    goto fail;
                break;
            }
            if (heap_push(q, e->until) < 0)
                goto fail;
        }
        if (PyList_Append(burst, e->message) < 0)
            goto fail;
        pop_front(q);
    }
    if (!PyList_GET_SIZE(burst)) {
        Py_DECREF(burst);
        burst = Py_None;
        Py_INCREF(burst);
    }
    return Py_BuildValue("(NN)", burst, late_ms);
fail:
    Py_DECREF(burst);
    Py_XDECREF(late_ms);
    return NULL;
}

PyDoc_STRVAR(turn_doc,
"turn(move_count, hold_ticks, freq) -> float | None\n\n"
"The MCU clock at which pump (with hold_after hold_ticks ahead) may send more of what\n"
"waits: when a slot frees if the move queue is full, else when the first waiting message\n"
"comes within hold_ticks of its time; None if nothing waits.");

static PyObject *mq_turn(MoveQueue *q, PyObject *args)
{
    Py_ssize_t move_count;
    double hold_ticks, freq;
    if (!PyArg_ParseTuple(args, "ndd", &move_count, &hold_ticks, &freq))
        return NULL;
    if (!q->len)
        Py_RETURN_NONE;
    if (q->used && q->used >= move_count)
        return PyFloat_FromDouble((double)q->heap[0] + QUEUE_MARGIN_S * freq);
    int64_t first = at(q, 0)->due;
    for (Py_ssize_t i = 1; i < q->len; i++)
        if (at(q, i)->due < first)
            first = at(q, i)->due;
    return PyFloat_FromDouble((double)first - hold_ticks);
}

PyDoc_STRVAR(full_doc,
"full(move_count) -> bool\n\n"
"Whether every slot of the MCU's move queue is taken (as last counted).");

static PyObject *mq_full(MoveQueue *q, PyObject *arg)
{
    Py_ssize_t move_count = PyLong_AsSsize_t(arg);
    if (move_count == -1 && PyErr_Occurred())
        return NULL;
    return PyBool_FromLong(q->used >= move_count);
}

PyDoc_STRVAR(busy_doc,
"busy(now) -> bool\n\nWhether a message waits or a slot is still taken at MCU clock now.");

static PyObject *mq_busy(MoveQueue *q, PyObject *arg)
{
    double now = PyFloat_AsDouble(arg);
    if (now == -1.0 && PyErr_Occurred())
        return NULL;
    if (q->len)
        Py_RETURN_TRUE;
    for (Py_ssize_t i = 0; i < q->used; i++)
        if ((double)q->heap[i] > now)
            Py_RETURN_TRUE;
    Py_RETURN_FALSE;
}

PyDoc_STRVAR(drop_doc, "drop()\n\nForget every waiting message (a stop).");

static PyObject *mq_drop(MoveQueue *q, PyObject *unused)
{
    (void)unused;
    while (q->len)
        pop_front(q);
    q->head = 0;
    Py_RETURN_NONE;
}

PyDoc_STRVAR(free_slots_doc,
"free_slots()\n\nEvery slot free (the MCU was configured afresh: its move queue is empty).");

static PyObject *mq_free_slots(MoveQueue *q, PyObject *unused)
{
    (void)unused;
    q->used = 0;
    Py_RETURN_NONE;
}

static PyObject *mq_waiting(MoveQueue *q, void *closure)
{
    (void)closure;
    return PyLong_FromSsize_t(q->len);
}

static PyObject *mq_in_use(MoveQueue *q, void *closure)
{
    (void)closure;
    return PyLong_FromSsize_t(q->used);
}

static int mq_init(MoveQueue *q, PyObject *args, PyObject *kwargs)
{
    static char *names[] = {"payload_max", NULL};
    Py_ssize_t payload_max;
    if (!PyArg_ParseTupleAndKeywords(args, kwargs, "n", names, &payload_max))
        return -1;
    q->payload_max = payload_max;
    return 0;
}

static void mq_dealloc(MoveQueue *q)
{
    while (q->len)
        pop_front(q);
    PyMem_Free(q->ring);
    PyMem_Free(q->heap);
    Py_TYPE(q)->tp_free((PyObject *)q);
}

static PyMethodDef mq_methods[] = {
    {"add", (PyCFunction)mq_add, METH_VARARGS, add_doc},
    {"extend", (PyCFunction)mq_extend, METH_O, extend_doc},
    {"pump_burst", (PyCFunction)mq_pump, METH_VARARGS, pump_doc},
    {"turn", (PyCFunction)mq_turn, METH_VARARGS, turn_doc},
    {"full", (PyCFunction)mq_full, METH_O, full_doc},
    {"busy", (PyCFunction)mq_busy, METH_O, busy_doc},
    {"drop", (PyCFunction)mq_drop, METH_NOARGS, drop_doc},
    {"free_slots", (PyCFunction)mq_free_slots, METH_NOARGS, free_slots_doc},
    {NULL, NULL, 0, NULL},
};

static PyGetSetDef mq_getset[] = {
    {"waiting", (getter)mq_waiting, NULL, "how many messages wait", NULL},
    {"in_use", (getter)mq_in_use, NULL, "how many slots are taken (as last counted)", NULL},
    {NULL, NULL, NULL, NULL, NULL},
};

static PyTypeObject MoveQueueType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "server.backends.klipper._stepcore.MoveQueueCore",
    .tp_doc = "The MCU's move queue seen from the host (see _movequeue.c).",
    .tp_basicsize = sizeof(MoveQueue),
    .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_BASETYPE,
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)mq_init,
    .tp_dealloc = (destructor)mq_dealloc,
    .tp_methods = mq_methods,
    .tp_getset = mq_getset,
};

int movequeue_add_type(PyObject *module)
{
    return stepcore_add_type(module, &MoveQueueType, "MoveQueueCore");
}
