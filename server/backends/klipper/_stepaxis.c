/* One stepper's steps from the trajectory to the wire, compiled (pins.py's Axis owns one): the
 * exact step clocks each sample solves for its spans are held here, in runs of one direction,
 * until schedule.py's flush finds them due; then they are compressed into queue_step runs and
 * encoded, with a reset_step_clock and a set_next_step_dir where needed, as the (message, slot
 * until, due) triples of the move queue. Each axis keeps where its steps are: piece_steps()
 * queues a piece's spans on every axis in one call, and each axis solves them in one call a
 * sample (add) and sends what is due in one (flush), where the Python it replaces made dozens:
 * a wake-up of the server costs what its Python touches.
 *
 * The arithmetic is _stepcore.c's (steps_solve_row, steps_compress: what solve() and
 * compress() compute) and the VLQs _wire.c's; the tests hold the messages to the generic
 * encoder's bytes and the steps to their exact times. */
#include "_stepcore.h"
#include <math.h>
#include <string.h>

typedef struct {
    PyObject_HEAD
    double *clocks;       /* held exact step clocks: clocks[head..len) */
    Py_ssize_t head, len, cap;
    int *seg_dir;         /* the held runs of one direction, in order: each one's direction */
    Py_ssize_t *seg_end;  /* ...and where it ends in clocks */
    Py_ssize_t nseg, dir_cap, end_cap;
    double *exact;        /* every clock added, when recording (tests, benchmarks) */
    Py_ssize_t exact_len, exact_cap;
    int record;
    int oid, invert_dir, sent_dir, needs_reset;
    double max_error;     /* ticks */
    int64_t last_clock;   /* the last step sent (MCU clock), and its exact clock */
    double last_exact;
    PyObject *step_prefix, *dir_prefix, *reset_prefix; /* the commands' id VLQs */
    int64_t position;     /* whole steps commanded so far */
    double per_mm;        /* steps per mm */
    double *spans;        /* the spans queued since the last add: 8 numbers each (steptimes.py) */
    Py_ssize_t *counts;   /* ...and the steps of each */
    Py_ssize_t nspans, spans_cap, counts_cap;
} StepAxis;

static int grow(void **buf, Py_ssize_t *cap, Py_ssize_t need, size_t item)
{
    if (need <= *cap)
        return 0;
    Py_ssize_t size = *cap ? *cap : 256;
    while (size < need)
        size *= 2;
    void *bigger = PyMem_Realloc(*buf, (size_t)size * item);
    if (bigger == NULL) {
        PyErr_NoMemory();
        return -1;
    }
    *buf = bigger;
    *cap = size;
    return 0;
}

/* Room for n more clocks (the consumed prefix dropped first). */
static int room_for(StepAxis *s, Py_ssize_t n)
{
    if (s->head && s->len + n > s->cap) {
        memmove(s->clocks, s->clocks + s->head, (size_t)(s->len - s->head) * sizeof(double));
        for (Py_ssize_t i = 0; i < s->nseg; i++)
            s->seg_end[i] -= s->head;
        s->len -= s->head;
        s->head = 0;
    }
    return grow((void **)&s->clocks, &s->cap, s->len + n, sizeof(double));
}

/* A span of count steps (row: steptimes.Spans' eight numbers) queued until add() solves it. */
static int queue_span(StepAxis *s, const double row[8], Py_ssize_t count)
{
    if (grow((void **)&s->spans, &s->spans_cap, 8 * (s->nspans + 1), sizeof(double)) < 0
        || grow((void **)&s->counts, &s->counts_cap, s->nspans + 1, sizeof(Py_ssize_t)) < 0)
        return -1;
    memcpy(s->spans + 8 * s->nspans, row, 8 * sizeof(double));
    s->counts[s->nspans++] = count;
    return 0;
}

/* The span from the whole step current to target (not equal) as Spans.add makes it. */
static int queue_steps(StepAxis *s, double x0, double u, double v0, double a,
                       double duration_s, int64_t current, int64_t target, double base_s)
{
    double direction = target > current ? 1.0 : -1.0;
    double row[8] = {x0, u, v0, a, duration_s, (double)current + 0.5 * direction, direction,
                     base_s};
    return queue_span(s, row, (Py_ssize_t)(target > current ? target - current
                                                               : current - target));
}

PyDoc_STRVAR(span_doc,
"span(x0, u, v0, a, duration_s, current, target, base_s)\n\n"
"Queue the steps from the whole step current to target along a piece, as steptimes.Spans.add\n"
"takes them (x0: steps at the piece's start, u: steps per mm of path); add() solves them.");

static PyObject *sa_span(StepAxis *s, PyObject *args)
{
    double x0, u, v0, a, duration_s, base_s;
    long long current, target;
    if (!PyArg_ParseTuple(args, "dddddLLd", &x0, &u, &v0, &a, &duration_s, &current, &target,
                          &base_s))
        return NULL;
    if (current != target && queue_steps(s, x0, u, v0, a, duration_s, current, target,
                                         base_s) < 0)
        return NULL;
    Py_RETURN_NONE;
}

PyDoc_STRVAR(add_doc,
"add(ref_clock, hz, ref_s) -> int\n\n"
"The spans queued since the last add (span(), piece_steps()): every step's exact clock,\n"
"solved as solve() does, held in runs of one direction; the count added.");

static PyObject *sa_add(StepAxis *s, PyObject *args)
{
    double ref_clock, hz, ref_s;
    if (!PyArg_ParseTuple(args, "ddd", &ref_clock, &hz, &ref_s))
        return NULL;
    Py_ssize_t nspans = s->nspans, added = 0;
    s->nspans = 0; /* solved now, or dropped with the error */
    double latest = -INFINITY;
    for (Py_ssize_t r = 0; r < nspans; r++) {
        const double *v = s->spans + 8 * r;
        Py_ssize_t count = s->counts[r];
        if (room_for(s, count) < 0)
            return NULL;
        steps_solve_row(v, count, s->clocks + s->len, &latest, ref_clock, hz, ref_s);
        if (s->record) {
            if (grow((void **)&s->exact, &s->exact_cap, s->exact_len + count, sizeof(double)) < 0)
                return NULL;
            memcpy(s->exact + s->exact_len, s->clocks + s->len, (size_t)count * sizeof(double));
            s->exact_len += count;
        }
        s->len += count;
        added += count;
        int direction = v[6] > 0.0 ? 1 : -1;
        if (s->nseg && s->seg_dir[s->nseg - 1] == direction) {
            s->seg_end[s->nseg - 1] = s->len;
            continue;
        }
        if (grow((void **)&s->seg_dir, &s->dir_cap, s->nseg + 1, sizeof(int)) < 0
            || grow((void **)&s->seg_end, &s->end_cap, s->nseg + 1, sizeof(Py_ssize_t)) < 0)
            return NULL;
        s->seg_dir[s->nseg] = direction;
        s->seg_end[s->nseg++] = s->len;
    }
    return PyLong_FromSsize_t(added);
}

static PyTypeObject StepAxisType;

/* args[first..first+n) as doubles into out; -1 with an exception set. */
static int doubles_of(PyObject *const *args, Py_ssize_t first, Py_ssize_t n, double *out)
{
    for (Py_ssize_t i = 0; i < n; i++) {
        PyObject *o = args[first + i];
        out[i] = PyFloat_CheckExact(o) ? PyFloat_AS_DOUBLE(o) : PyFloat_AsDouble(o);
    }
    return PyErr_Occurred() ? -1 : 0;
}

/* A tuple of n numbers (a piece's start or unit) as doubles, or -1 with an exception set. */
static int vector_of(PyObject *tuple, Py_ssize_t n, double *out)
{
    if (!PyTuple_Check(tuple) || PyTuple_GET_SIZE(tuple) != n) {
        PyErr_SetString(PyExc_ValueError, "a piece's vectors have one number per axis");
        return -1;
    }
    return doubles_of(((PyTupleObject *)tuple)->ob_item, 0, n, out);
}

#define AXES_MAX 16

/* The step axes (a tuple of at most AXES_MAX) into out and a piece's vector (start or unit)
 * as doubles, checked; their count, or -1 with an exception set. */
static Py_ssize_t axes_and(PyObject *axes, PyObject *vector, StepAxis **out, double *values)
{
    Py_ssize_t n = PyTuple_Check(axes) ? PyTuple_GET_SIZE(axes) : AXES_MAX + 1;
    for (Py_ssize_t i = 0; i < n && n <= AXES_MAX; i++) {
        PyObject *item = PyTuple_GET_ITEM(axes, i);
        if (!PyObject_TypeCheck(item, &StepAxisType))
            n = AXES_MAX + 1;
        else
            out[i] = (StepAxis *)item;
    }
    if (n > AXES_MAX) {
        PyErr_SetString(PyExc_TypeError, "axes is a tuple of at most 16 StepAxis");
        return -1;
    }
    return vector_of(vector, n, values) < 0 ? -1 : n;
}

PyDoc_STRVAR(piece_steps_doc,
"piece_steps(axes, start_mm, unit, v0, a, rel_s, base_s)\n\n"
"Each axis' whole steps along a piece (schedule.py: its start, unit vector, speed and\n"
"acceleration) up to rel_s into it: the axis is commanded round_half_up(steps at the path's\n"
"distance), and the steps from its position to there are queued as one span (span()) of the\n"
"piece that starts at print time base_s; its position follows. add() solves them. Nothing\n"
"is queued when an argument is refused.");

static PyObject *piece_steps(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)self;
    StepAxis *axes[AXES_MAX];
    double start[AXES_MAX], unit[AXES_MAX], v[4];
    int64_t target[AXES_MAX];
    if (nargs != 7) {
        PyErr_SetString(PyExc_TypeError, "piece_steps takes 7 arguments");
        return NULL;
    }
    Py_ssize_t n = axes_and(args[0], args[1], axes, start);
    if (n < 0 || vector_of(args[2], n, unit) < 0 || doubles_of(args, 3, 4, v) < 0)
        return NULL;
    double v0 = v[0], a = v[1], rel_s = v[2], base_s = v[3];
    double distance = v0 * rel_s + 0.5 * a * rel_s * rel_s;
    for (Py_ssize_t i = 0; i < n; i++) { /* every target first: all or nothing */
        StepAxis *s = axes[i];
        double x0 = start[i] * s->per_mm, u = unit[i] * s->per_mm;
        double at = floor(x0 + u * distance + 0.5); /* steptimes.step_target */
        if (unit[i] != 0.0 && !(fabs(at) < 9e15)) {
            PyErr_SetString(PyExc_ValueError, "a piece's steps are not finite");
            return NULL;
        }
        target[i] = unit[i] != 0.0 ? (int64_t)at : s->position;
    }
    for (Py_ssize_t i = 0; i < n; i++) {
        StepAxis *s = axes[i];
        if (target[i] == s->position)
            continue;
        if (queue_steps(s, start[i] * s->per_mm, unit[i] * s->per_mm, v0, a, rel_s,
                        s->position, target[i], base_s) < 0)
            return NULL;
        s->position = target[i];
    }
    Py_RETURN_NONE;
}

PyDoc_STRVAR(off_track_doc,
"off_track(axes, start_mm) -> bool\n\n"
"Whether a piece starting at start_mm starts more than a step away from where some axis'\n"
"steps are (the position was redefined: schedule.py rebases it).");

static PyObject *off_track(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)self;
    StepAxis *axes[AXES_MAX];
    double start[AXES_MAX];
    if (nargs != 2) {
        PyErr_SetString(PyExc_TypeError, "off_track takes 2 arguments");
        return NULL;
    }
    Py_ssize_t n = axes_and(args[0], args[1], axes, start);
    if (n < 0)
        return NULL;
    for (Py_ssize_t i = 0; i < n; i++)
        if (fabs(start[i] * axes[i]->per_mm - (double)axes[i]->position) > 1.0)
            Py_RETURN_TRUE;
    Py_RETURN_FALSE;
}

/* The clock from which what is held must be looked at (something is): its first step's; 0
 * when at once (runs both ways wait). */
static double first_clock(StepAxis *s)
{
    return s->nseg > 1 ? 0.0 : s->clocks[s->head];
}

PyDoc_STRVAR(first_clock_doc,
"first_clock() -> float | None\n\n"
"The clock from which what this axis holds must be looked at: its first step's, 0 when at\n"
"once (runs both ways wait), None when it holds nothing.");

static PyObject *sa_first_clock(StepAxis *s, PyObject *unused)
{
    (void)unused;
    if (!s->nseg)
        Py_RETURN_NONE;
    return PyFloat_FromDouble(first_clock(s));
}

static PyObject *message(PyObject *prefix, int64_t a, int64_t b)
{
    int64_t values[] = {a, b};
    return wire_encode(prefix, values, 2);
}

/* (message, slot until, due) onto out: a message that takes a slot of the MCU's move queue
 * (a queue_step) holds it until it is due; the others take none (until None). */
static int append_triple(PyObject *out, PyObject *message, int takes_slot, int64_t due)
{
    if (message == NULL)
        return -1;
    PyObject *item = takes_slot ? Py_BuildValue("(NLL)", message, (long long)due, (long long)due)
                                : Py_BuildValue("(NOL)", message, Py_None, (long long)due);
    if (item == NULL || PyList_Append(out, item) < 0) {
        Py_XDECREF(item);
        return -1;
    }
    Py_DECREF(item);
    return 0;
}

typedef struct {
    StepAxis *axis;
    PyObject *out;
} Sink;

/* Each run as its queue_step, due (and its slot taken until) its first step. */
static int encode_run(void *ctx, Run run, int64_t first_clock)
{
    Sink *sink = ctx;
    int64_t values[] = {sink->axis->oid, run.interval, run.count, run.add};
    return append_triple(sink->out, wire_encode(sink->axis->step_prefix, values, 4), 1,
                         first_clock);
}

static PyObject *doubles(const double *values, Py_ssize_t n)
{
    PyObject *raw = PyBytes_FromStringAndSize((const char *)values,
                                              n * (Py_ssize_t)sizeof(double));
    if (raw == NULL)
        return NULL;
    PyObject *view = PyMemoryView_FromObject(raw);
    Py_DECREF(raw);
    if (view == NULL)
        return NULL;
    PyObject *cast = PyObject_CallMethod(view, "cast", "s", "d");
    Py_DECREF(view);
    return cast;
}

/* Runs for a prefix of points (one direction), the reset and direction messages they need
 * first, into out; how many points they cover, or -1. */
static Py_ssize_t emit(StepAxis *s, int direction, const double *points, Py_ssize_t n,
                       int final, PyObject *out, PyObject *errors)
{
    if (s->needs_reset || points[0] - (double)s->last_clock > 1073741824.0) {
        int64_t start = (int64_t)(points[0] - s->max_error) - 1;
        s->last_clock = start;
        s->last_exact = (double)start;
        if (append_triple(out, message(s->reset_prefix, s->oid, start & 0xFFFFFFFF), 0,
                          start) < 0)
            return -1;
        s->needs_reset = 0;
    }
    if (direction != s->sent_dir) { /* due with the first step it turns */
        if (append_triple(out, message(s->dir_prefix, s->oid, (direction > 0) != s->invert_dir),
                          0, (int64_t)points[0]) < 0)
            return -1;
        s->sent_dir = direction;
    }
    double *early = NULL;
    if (errors != Py_None && (early = PyMem_Malloc((size_t)n * sizeof(double))) == NULL) {
        PyErr_NoMemory();
        return -1;
    }
    Sink sink = {s, out};
    Py_ssize_t done = steps_compress(points, n, &s->last_clock, &s->last_exact, s->max_error,
                                     final, early, encode_run, &sink);
    if (done > 0 && early != NULL) {
        PyObject *view = doubles(early, done);
        if (view == NULL || PyList_Append(errors, view) < 0)
            done = -1;
        Py_XDECREF(view);
    }
    PyMem_Free(early);
    return done;
}

PyDoc_STRVAR(flush_doc,
"flush(force_clock, idle, out, errors)\n\n"
"What is due: unless idle (everything goes), nothing while what is held runs one way and its\n"
"first step is not before force_clock (its run may still grow). Else, run by run: the runs\n"
"complete before the last step held go; the last run waits while its own first step is not\n"
"before force_clock (it grows). Appends (message, slot until, due) triples to out; with\n"
"errors (a list), how early each step sent lands (ticks, an array a call).");

static PyObject *sa_flush(StepAxis *s, PyObject *args)
{
    double force;
    int idle;
    PyObject *out, *errors;
    if (!PyArg_ParseTuple(args, "dpO!O", &force, &idle, &PyList_Type, &out, &errors))
        return NULL;
    if (s->step_prefix == NULL) {
        PyErr_SetString(PyExc_RuntimeError, "the axis is not configured");
        return NULL;
    }
    if (!idle && (!s->nseg || first_clock(s) >= force))
        Py_RETURN_NONE; /* nothing due: its run may still grow */
    while (s->nseg) {
        const double *points = s->clocks + s->head;
        Py_ssize_t n = s->seg_end[0] - s->head;
        int direction = s->seg_dir[0], final = idle || s->nseg > 1;
        if (!(final || points[0] < force))
            break;
        Py_ssize_t done = emit(s, direction, points, n, final, out, errors);
        if (done < 0)
            return NULL;
        if (done < n && points[done] < force) { /* the last run is due */
            Py_ssize_t more = emit(s, direction, points + done, n - done, 1, out, errors);
            if (more < 0)
                return NULL;
            done += more;
        }
        s->head += done;
        if (done < n)
            break;
        memmove(s->seg_dir, s->seg_dir + 1, (size_t)(s->nseg - 1) * sizeof(int));
        memmove(s->seg_end, s->seg_end + 1, (size_t)(s->nseg - 1) * sizeof(Py_ssize_t));
        s->nseg--;
    }
    if (!s->nseg)
        s->head = s->len = 0;
    Py_RETURN_NONE;
}

PyDoc_STRVAR(configure_doc,
"configure(oid, invert_dir, max_error, queue_step, set_next_step_dir, reset_step_clock)\n\n"
"The stepper's oid and direction pin, the compression's bound (ticks) and each command's id\n"
"VLQ (Dictionary.step_prefixes); the next steps start with a reset_step_clock.");

static PyObject *sa_configure(StepAxis *s, PyObject *args)
{
    int oid, invert;
    double max_error;
    PyObject *step, *dir, *reset;
    if (!PyArg_ParseTuple(args, "ipdSSS", &oid, &invert, &max_error, &step, &dir, &reset))
        return NULL;
    if (PyBytes_GET_SIZE(step) > 8 || PyBytes_GET_SIZE(dir) > 8 || PyBytes_GET_SIZE(reset) > 8) {
        PyErr_SetString(PyExc_ValueError, "a message id prefix is at most 8 bytes");
        return NULL;
    }
    s->oid = oid;
    s->invert_dir = invert;
    s->max_error = max_error;
    Py_INCREF(step);
    Py_INCREF(dir);
    Py_INCREF(reset);
    Py_XSETREF(s->step_prefix, step);
    Py_XSETREF(s->dir_prefix, dir);
    Py_XSETREF(s->reset_prefix, reset);
    s->needs_reset = 1;
    s->sent_dir = 0;
    Py_RETURN_NONE;
}

PyDoc_STRVAR(restart_doc,
"restart()\n\n"
"The MCU's stepper was reset (a new configuration): the next steps start with a\n"
"reset_step_clock and a set_next_step_dir.");

static PyObject *sa_restart(StepAxis *s, PyObject *unused)
{
    (void)unused;
    s->needs_reset = 1;
    s->sent_dir = 0;
    Py_RETURN_NONE;
}

PyDoc_STRVAR(clear_doc, "clear()\n\nDrop every step held (a stop).");

static PyObject *sa_clear(StepAxis *s, PyObject *unused)
{
    (void)unused;
    s->head = s->len = s->nseg = s->nspans = 0;
    Py_RETURN_NONE;
}

PyDoc_STRVAR(recorded_doc,
"recorded() -> memoryview\n\n"
"Every exact clock added since the axis was made (float64), when made with record=True.");

static PyObject *sa_recorded(StepAxis *s, PyObject *unused)
{
    (void)unused;
    return doubles(s->exact, s->exact_len);
}

static PyObject *sa_held(StepAxis *s, void *closure)
{
    (void)closure;
    return PyLong_FromSsize_t(s->len - s->head);
}

static PyObject *sa_last_clock(StepAxis *s, void *closure)
{
    (void)closure;
    return PyLong_FromLongLong((long long)s->last_clock);
}

static int sa_init(StepAxis *s, PyObject *args, PyObject *kwargs)
{
    static char *names[] = {"record", NULL};
    int record = 0;
    if (!PyArg_ParseTupleAndKeywords(args, kwargs, "|p", names, &record))
        return -1;
    s->record = record;
    s->max_error = 1.0;
    s->needs_reset = 1;
    s->per_mm = 1.0;
    return 0;
}

static void sa_dealloc(StepAxis *s)
{
    PyMem_Free(s->clocks);
    PyMem_Free(s->seg_dir);
    PyMem_Free(s->seg_end);
    PyMem_Free(s->exact);
    PyMem_Free(s->spans);
    PyMem_Free(s->counts);
    Py_XDECREF(s->step_prefix);
    Py_XDECREF(s->dir_prefix);
    Py_XDECREF(s->reset_prefix);
    Py_TYPE(s)->tp_free((PyObject *)s);
}

static PyMethodDef sa_methods[] = {
    {"span", (PyCFunction)sa_span, METH_VARARGS, span_doc},
    {"add", (PyCFunction)sa_add, METH_VARARGS, add_doc},
    {"first_clock", (PyCFunction)sa_first_clock, METH_NOARGS, first_clock_doc},
    {"flush", (PyCFunction)sa_flush, METH_VARARGS, flush_doc},
    {"configure", (PyCFunction)sa_configure, METH_VARARGS, configure_doc},
    {"restart", (PyCFunction)sa_restart, METH_NOARGS, restart_doc},
    {"clear", (PyCFunction)sa_clear, METH_NOARGS, clear_doc},
    {"recorded", (PyCFunction)sa_recorded, METH_NOARGS, recorded_doc},
    {NULL, NULL, 0, NULL},
};

static PyObject *sa_get_record(StepAxis *s, void *closure)
{
    (void)closure;
    return PyBool_FromLong(s->record);
}

static int sa_set_record(StepAxis *s, PyObject *value, void *closure)
{
    (void)closure;
    int on = value == NULL ? 0 : PyObject_IsTrue(value);
    if (on < 0)
        return -1;
    s->record = on;
    return 0;
}

static PyObject *sa_get_position(StepAxis *s, void *closure)
{
    (void)closure;
    return PyLong_FromLongLong((long long)s->position);
}

static int sa_set_position(StepAxis *s, PyObject *value, void *closure)
{
    (void)closure;
    long long position = value == NULL ? -1 : PyLong_AsLongLong(value);
    if (value == NULL)
        PyErr_SetString(PyExc_AttributeError, "position cannot be deleted");
    if (PyErr_Occurred())
        return -1;
    s->position = position;
    return 0;
}

static PyObject *sa_get_per_mm(StepAxis *s, void *closure)
{
    (void)closure;
    return PyFloat_FromDouble(s->per_mm);
}

static int sa_set_per_mm(StepAxis *s, PyObject *value, void *closure)
{
    (void)closure;
    double per_mm = value == NULL ? -1.0 : PyFloat_AsDouble(value);
    if (value == NULL)
        PyErr_SetString(PyExc_AttributeError, "steps_per_mm cannot be deleted");
    if (PyErr_Occurred())
        return -1;
    if (!(per_mm > 0.0 && isfinite(per_mm))) {
        PyErr_SetString(PyExc_ValueError, "steps_per_mm is a positive number");
        return -1;
    }
    s->per_mm = per_mm;
    return 0;
}

static PyGetSetDef sa_getset[] = {
    {"position", (getter)sa_get_position, (setter)sa_set_position,
     "whole steps commanded so far", NULL},
    {"steps_per_mm", (getter)sa_get_per_mm, (setter)sa_set_per_mm, "steps per mm", NULL},
    {"record", (getter)sa_get_record, (setter)sa_set_record,
     "whether every clock added is kept (recorded())", NULL},
    {"held", (getter)sa_held, NULL, "how many steps are held (not yet sent)", NULL},
    {"last_clock", (getter)sa_last_clock, NULL, "the MCU clock of the last step sent", NULL},
    {NULL, NULL, NULL, NULL, NULL},
};

static PyMethodDef module_functions[] = {
    {"piece_steps", (PyCFunction)(void (*)(void))piece_steps, METH_FASTCALL, piece_steps_doc},
    {"off_track", (PyCFunction)(void (*)(void))off_track, METH_FASTCALL, off_track_doc},
    {NULL, NULL, 0, NULL},
};

static PyTypeObject StepAxisType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "server.backends.klipper._stepcore.StepAxis",
    .tp_doc = "One stepper's steps from the trajectory to the wire (see _stepaxis.c).",
    .tp_basicsize = sizeof(StepAxis),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)sa_init,
    .tp_dealloc = (destructor)sa_dealloc,
    .tp_methods = sa_methods,
    .tp_getset = sa_getset,
};

int stepaxis_add_type(PyObject *module)
{
    if (PyModule_AddFunctions(module, module_functions) < 0)
        return -1;
    return stepcore_add_type(module, &StepAxisType, "StepAxis");
}
