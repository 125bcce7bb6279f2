/* The Klipper backend's step core, compiled: exact step times and their compression into
 * queue_step runs; and (_wire.c) the wire's hot end: VLQ messages, framed and checksummed
 * blocks. The algorithms and their explanation are in steptimes.py and
 * stepcompress.py (which call this); tests/support/stepcore_reference.py holds the same
 * arithmetic in numpy, and the tests hold this module to it exactly.
 *
 * No numpy C API: arrays come and go through the buffer protocol (C-contiguous float64).
 * Built with -ffp-contract=off so no fused multiply-add changes a rounding. */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

#include "_stepcore.h"

/* The wire's hot end, in _wire.c (one module, two files) */
void wire_init(void);
PyObject *wire_message(PyObject *self, PyObject *const *args, Py_ssize_t nargs);
PyObject *wire_crc16(PyObject *self, PyObject *arg);
PyObject *wire_frame(PyObject *self, PyObject *args);
int serialq_add_type(PyObject *module);
extern const char message_doc[], crc16_doc[], frame_doc[];

#define MAX_COUNT 65535
#define ADD_MIN (-32768)
#define ADD_MAX 32767
#define WINDOW 1024
#define QUADRATIC_DEV 11
#define MAX_TRIES 48
#define SPREAD_HUGE ((int64_t)1 << 40) /* beyond any add range: no narrowing */

/* floor(a / b) for b > 0, as Python's // */
static inline int64_t floordiv(int64_t a, int64_t b)
{
    int64_t q = a / b;
    if ((a % b) != 0 && a < 0)
        q--;
    return q;
}

/* -- compression ------------------------------------------------------------------------- */

/* The windows [lo, hi] of a run's candidate steps, computed lazily up to where a search
 * looks (each step's window depends only on it, the step before and the run's start). */
typedef struct {
    const double *points;
    Py_ssize_t len, ready;
    int64_t *lo, *hi;
    double last_clock, previous, max_error;
} Windows;

static void windows_upto(Windows *w, Py_ssize_t upto)
{
    if (upto > w->len)
        upto = w->len;
    for (Py_ssize_t i = w->ready; i < upto; i++) {
        double p = w->points[i];
        double q = p - w->last_clock;
        double gap = p - (i ? w->points[i - 1] : w->previous);
        double half = 0.5 * (gap > 0.0 ? gap : 0.0);
        double err = half < w->max_error ? half : w->max_error;
        double h = floor(q);
        if (h < 1.0)
            h = 1.0;
        int64_t hi = (int64_t)h;
        int64_t lo = (int64_t)ceil(q - err);
        if (lo > hi)
            lo = hi;
        if (lo < 1)
            lo = 1;
        w->lo[i] = lo;
        w->hi[i] = hi;
    }
    if (upto > w->ready)
        w->ready = upto;
}

/* The longest run from the start that `add` allows: its count, and its interval. */
static Py_ssize_t longest_run(Windows *w, int64_t add, int64_t *interval)
{
    int64_t ilo = 0, ihi = 0;
    for (Py_ssize_t i = 0; i < w->len; i++) {
        if (i >= w->ready)
            windows_upto(w, i + 64 + w->ready);
        int64_t m = (int64_t)i + 1;
        int64_t tri = m * (m - 1) / 2 * add;
        int64_t clo = -floordiv(tri - w->lo[i], m); /* ceil((lo - tri) / m) */
        int64_t chi = floordiv(w->hi[i] - tri, m);
        if (i) {
            if (clo < ilo)
                clo = ilo;
            if (chi > ihi)
                chi = ihi;
        }
        if (clo > chi) {
            *interval = i ? ihi : 0;
            return i;
        }
        ilo = clo;
        ihi = chi;
    }
    *interval = ihi;
    return w->len;
}

static Run best_run(Windows *w)
{
    int64_t min_add = ADD_MIN, max_add = ADD_MAX, add = 0, best_reach = -1;
    Run best = {0, 0, 0}, zero = {0, 0, 0};
    double spread_all = w->max_error * QUADRATIC_DEV;
    int huge = !(spread_all < 1e18 && spread_all > -1e18);
    int64_t spread_base = huge ? 0 : (int64_t)spread_all;
    for (int tries = 0; tries < MAX_TRIES; tries++) {
        int64_t interval;
        int64_t count = longest_run(w, add, &interval);
        if (count == w->len)
            return (Run){interval, count, add};
        int64_t reach = add * (count * (count - 1) / 2) + interval * count;
        if (count && (reach > best_reach || (reach == best_reach && interval > best.interval))) {
            best = (Run){interval, count, add};
            best_reach = reach;
            if (add == 0)
                zero = best;
        }
        int64_t m = count + 1; /* the first step it misses */
        if (add * (m * (m - 1) / 2) + interval * m < w->lo[count])
            min_add = add + 1; /* that step comes too early: more add */
        else
            max_add = add - 1;
        if (count > 1) {
            int64_t spread = huge ? SPREAD_HUGE : floordiv(spread_base, count * count);
            if (spread > SPREAD_HUGE)
                spread = SPREAD_HUGE;
            if (add - spread > min_add)
                min_add = add - spread;
            if (add + spread < max_add)
                max_add = add + spread;
        }
        if (min_add > max_add)
            break;
        add = max_add - floordiv(max_add - min_add, 4);
    }
    if (zero.count && zero.count + zero.count / 16 >= best.count)
        return zero;
    return best;
}

static int get_doubles(PyObject *obj, Py_buffer *view, int writable, const char *what)
{
    int flags = PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0);
    if (PyObject_GetBuffer(obj, view, flags) < 0)
        return -1;
    if (view->itemsize != 8 || view->format == NULL || strcmp(view->format, "d") != 0) {
        PyBuffer_Release(view);
        PyErr_Format(PyExc_TypeError, "%s: a contiguous float64 array is needed", what);
        return -1;
    }
    return 0;
}

PyDoc_STRVAR(compress_doc,
"compress(points, last_clock, last_exact, max_error, final, errors)\n"
"-> (runs, done, last_clock, last_exact)\n\n"
"queue_step runs (interval, count, add) for a prefix of points; errors: None or a float64\n"
"array as long as points that gets each covered step's early-ness (ticks).");

Py_ssize_t steps_compress(const double *points, Py_ssize_t n, int64_t *last_clock,
                          double *last_exact, double max_error, int final, double *errors,
                          RunSink sink, void *ctx)
{
    Py_ssize_t done = 0, cap = n < MAX_COUNT ? n : MAX_COUNT;
    int64_t *lohi = PyMem_Malloc(sizeof(int64_t) * 2 * (size_t)(cap ? cap : 1));
    if (lohi == NULL) {
        PyErr_NoMemory();
        return -1;
    }
    int64_t last = *last_clock;
    Py_ssize_t size = WINDOW;
    while (done < n) {
        Windows w = {points + done, n - done < size ? n - done : size, 0, lohi, lohi + cap,
                     (double)last, *last_exact, max_error};
        Run run = best_run(&w);
        if (run.count == w.len && w.len < n - done && size < MAX_COUNT) {
            size = size * 4 < MAX_COUNT ? size * 4 : MAX_COUNT; /* it may reach further */
            continue;
        }
        size = WINDOW;
        if (!final && done + run.count == n)
            break;
        if (sink(ctx, run, last + run.interval) < 0) {
            PyMem_Free(lohi);
            return -1;
        }
        if (errors) {
            for (int64_t k = 0; k < run.count; k++) {
                int64_t clock = last + (k + 1) * run.interval + run.add * (k * (k + 1) / 2);
                errors[done + k] = points[done + k] - (double)clock;
            }
        }
        last += run.count * run.interval + run.add * ((run.count - 1) * run.count / 2);
        *last_clock = last;
        *last_exact = points[done + run.count - 1];
        done += run.count;
    }
    PyMem_Free(lohi);
    return done;
}

/* compress()'s sink: each run as an (interval, count, add) tuple in a list */
static int append_run(void *ctx, Run run, int64_t first_clock)
{
    (void)first_clock;
    PyObject *item = Py_BuildValue("(LLL)", (long long)run.interval, (long long)run.count,
                                   (long long)run.add);
    if (item == NULL || PyList_Append((PyObject *)ctx, item) < 0) {
        Py_XDECREF(item);
        return -1;
    }
    Py_DECREF(item);
    return 0;
}

static PyObject *compress(PyObject *self, PyObject *args)
{
    (void)self;
    PyObject *points_obj, *errors_obj;
    long long last_clock;
    double last_exact, max_error;
    int final;
    if (!PyArg_ParseTuple(args, "OLddpO", &points_obj, &last_clock, &last_exact, &max_error,
                          &final, &errors_obj))
        return NULL;
    Py_buffer pv, ev;
    if (get_doubles(points_obj, &pv, 0, "points") < 0)
        return NULL;
    int want_errors = errors_obj != Py_None;
    if (want_errors) {
        if (get_doubles(errors_obj, &ev, 1, "errors") < 0) {
            PyBuffer_Release(&pv);
            return NULL;
        }
        if (ev.len < pv.len) {
            PyBuffer_Release(&pv);
            PyBuffer_Release(&ev);
            PyErr_SetString(PyExc_ValueError, "errors is shorter than points");
            return NULL;
        }
    }
    PyObject *runs = PyList_New(0);
    int64_t last = last_clock;
    Py_ssize_t done = runs == NULL ? -1 : steps_compress(
        pv.buf, pv.len / 8, &last, &last_exact, max_error, final,
        want_errors ? ev.buf : NULL, append_run, runs);
    PyBuffer_Release(&pv);
    if (want_errors)
        PyBuffer_Release(&ev);
    if (done < 0) {
        Py_XDECREF(runs);
        return NULL;
    }
    return Py_BuildValue("(NnLd)", runs, done, (long long)last, last_exact);
}

/* -- step times -------------------------------------------------------------------------- */

void steps_solve_row(const double v[8], Py_ssize_t count, double *out, double *latest,
                     double ref_clock, double hz, double ref_s)
{
    double x0 = v[0], u = v[1], v0 = v[2], a = v[3], duration = v[4], first = v[5];
    double direction = v[6], base = v[7];
    for (Py_ssize_t k = 0; k < count; k++) {
        double boundary = first + direction * (double)k;
        double distance = (boundary - x0) / u;
        if (!(distance > 0.0))
            distance = 0.0;
        double square = v0 * v0 + 2.0 * a * distance;
        double root = sqrt(square > 0.0 ? square : 0.0);
        double speed = v0 + root;
        double t = 2.0 * distance / (speed > 1e-300 ? speed : 1e-300);
        if (t < 0.0)
            t = 0.0;
        if (t > duration)
            t = duration;
        t = base + t;
        if (t < *latest)
            t = *latest; /* rounding never puts a step before the one before */
        *latest = t;
        out[k] = ref_clock + hz * (t - ref_s);
    }
}

/* A span's row (steptimes.Spans: a tuple of 8 numbers) into v; -1 with an exception set. */
static int steps_row(PyObject *row, double v[8])
{
    if (!PyTuple_Check(row) || PyTuple_GET_SIZE(row) != 8) {
        PyErr_SetString(PyExc_TypeError, "a row is a tuple of 8 numbers");
        return -1;
    }
    for (int i = 0; i < 8; i++) {
        PyObject *o = PyTuple_GET_ITEM(row, i);
        v[i] = PyFloat_CheckExact(o) ? PyFloat_AS_DOUBLE(o) : PyFloat_AsDouble(o);
    }
    return PyErr_Occurred() ? -1 : 0;
}

PyDoc_STRVAR(solve_doc,
"solve(rows, counts, out, ref_clock, hz, ref_s)\n\n"
"Every step's time of the spans (rows: (x0, u, v0, a, duration, first boundary, direction,\n"
"base) tuples; counts: steps of each) into out (float64, sum(counts) long), non-decreasing,\n"
"mapped to ref_clock + hz * (t - ref_s).");

static PyObject *solve(PyObject *self, PyObject *args)
{
    (void)self;
    PyObject *rows, *counts, *out_obj;
    double ref_clock, hz, ref_s;
    if (!PyArg_ParseTuple(args, "O!O!Oddd", &PyList_Type, &rows, &PyList_Type, &counts,
                          &out_obj, &ref_clock, &hz, &ref_s))
        return NULL;
    Py_ssize_t nrows = PyList_GET_SIZE(rows);
    if (PyList_GET_SIZE(counts) != nrows) {
        PyErr_SetString(PyExc_ValueError, "rows and counts differ in length");
        return NULL;
    }
    Py_buffer ov;
    if (get_doubles(out_obj, &ov, 1, "out") < 0)
        return NULL;
    double *out = ov.buf, latest = -INFINITY;
    Py_ssize_t room = ov.len / 8, at = 0;
    for (Py_ssize_t r = 0; r < nrows; r++) {
        double v[8];
        if (steps_row(PyList_GET_ITEM(rows, r), v) < 0)
            goto fail;
        Py_ssize_t count = PyLong_AsSsize_t(PyList_GET_ITEM(counts, r));
        if (PyErr_Occurred())
            goto fail;
        if (count < 0 || count > room - at) {
            PyErr_SetString(PyExc_ValueError, "out is shorter than the steps");
            goto fail;
        }
        steps_solve_row(v, count, out + at, &latest, ref_clock, hz, ref_s);
        at += count;
    }
    PyBuffer_Release(&ov);
    return PyLong_FromSsize_t(at);
fail:
    PyBuffer_Release(&ov);
    return NULL;
}


static PyMethodDef methods[] = {
    {"compress", compress, METH_VARARGS, compress_doc},
    {"solve", solve, METH_VARARGS, solve_doc},
    {"message", (PyCFunction)(void (*)(void))wire_message, METH_FASTCALL, message_doc},
    {"crc16", wire_crc16, METH_O, crc16_doc},
    {"frame", wire_frame, METH_VARARGS, frame_doc},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_stepcore",
    "The Klipper backend's step times and step compression, compiled (see _stepcore.c).", -1,
    methods, NULL, NULL, NULL, NULL,
};

int stepcore_add_type(PyObject *module, PyTypeObject *type, const char *name)
{
    if (PyType_Ready(type) < 0)
        return -1;
    Py_INCREF(type);
    if (PyModule_AddObject(module, name, (PyObject *)type) < 0) {
        Py_DECREF(type);
        return -1;
    }
    return 0;
}

PyMODINIT_FUNC PyInit__stepcore(void)
{
    wire_init();
    PyObject *m = PyModule_Create(&module);
    if (m == NULL)
        return NULL;
    /* the compression's constants, for the Python side to name (stepcompress.py) */
    if (PyModule_AddIntConstant(m, "MAX_COUNT", MAX_COUNT) < 0
        || PyModule_AddIntConstant(m, "ADD_MIN", ADD_MIN) < 0
        || PyModule_AddIntConstant(m, "ADD_MAX", ADD_MAX) < 0
        || PyModule_AddIntConstant(m, "WINDOW", WINDOW) < 0
        || PyModule_AddIntConstant(m, "QUADRATIC_DEV", QUADRATIC_DEV) < 0
        || PyModule_AddIntConstant(m, "MAX_TRIES", MAX_TRIES) < 0
        || serialq_add_type(m) < 0 || stepaxis_add_type(m) < 0
        || movequeue_add_type(m) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
