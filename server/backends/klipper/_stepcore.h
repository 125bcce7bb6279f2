/* What the step core's C files share (one module: _stepcore.c, _wire.c, _stepaxis.c,
 * _movequeue.c). */
#ifndef MOTIOND_STEPCORE_H
#define MOTIOND_STEPCORE_H
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdint.h>

/* One queue_step: count steps, the first interval ticks after the last step, + add each. */
typedef struct {
    int64_t interval, count, add;
} Run;

/* Told each run as it is made, with the clock of its first step; -1 (an exception set)
 * stops the compression. */
typedef int (*RunSink)(void *ctx, Run run, int64_t first_clock);

/* queue_step runs for a prefix of points[0..n) (exact step clocks, one direction,
 * ascending) from the stepper's last step (*last_clock, *last_exact: advanced past each run
 * told); unless final, a last run that reaches the end of points is held back. With errors
 * (as long as points), each covered step's early-ness (ticks). Returns how many points the
 * runs cover, or -1 with an exception set. (_stepcore.c; stepcompress.py explains it.) */
Py_ssize_t steps_compress(const double *points, Py_ssize_t n, int64_t *last_clock,
                          double *last_exact, double max_error, int final, double *errors,
                          RunSink sink, void *ctx);

/* The count steps of one span (v: x0, u, v0, a, duration, first boundary, direction, base)
 * into out, each no earlier than *latest (which follows them), as MCU clocks
 * ref_clock + hz * (t - ref_s). (_stepcore.c; steptimes.py explains it.) */
void steps_solve_row(const double v[8], Py_ssize_t count, double *out, double *latest,
                     double ref_clock, double hz, double ref_s);

/* A message: prefix (a command's id VLQ, bytes of at most 8) and the VLQs of count (at most
 * 16) values. (_wire.c) */
PyObject *wire_encode(PyObject *prefix, const int64_t *values, Py_ssize_t count);

/* type, made ready, into module as name. (_stepcore.c) */
int stepcore_add_type(PyObject *module, PyTypeObject *type, const char *name);

/* The StepAxis type into the module. (_stepaxis.c) */
int stepaxis_add_type(PyObject *module);

/* The MoveQueueCore type into the module. (_movequeue.c) */
int movequeue_add_type(PyObject *module);

#endif
