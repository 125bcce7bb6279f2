/* The wire's hot end of the Klipper backend, compiled into the step core's module (see
 * _stepcore.c): a prepared message's VLQs (_stepaxis.c's messages too), a block's framing
 * and its crc16. codec.py and dictionary.py hold the protocol's description; the tests hold
 * these to the generic Python encoder and to klippy's own msgproto, byte for byte. The
 * functions below that are not static are declared in _stepcore.c, which names them. */
#include "_stepcore.h"
#include <string.h>


/* `value` as Klipper's VLQ: 7 bits a byte, most significant first, by size (as vlq() in
 * dictionary.py: -2**31 .. 2**32-1, and the same bits for anything else that fits 64 bits). */
static inline Py_ssize_t put_vlq(uint8_t *out, int64_t value)
{
    int size = 5;
    if (value >= -0x20 && value < 0x60)
        size = 1;
    else if (value >= -0x1000 && value < 0x3000)
        size = 2;
    else if (value >= -0x80000 && value < 0x180000)
        size = 3;
    else if (value >= -0x4000000 && value < 0xC000000)
        size = 4;
    uint64_t bits = (uint64_t)value; /* two's complement: the low 35 bits are what is sent */
    for (int i = size - 1; i > 0; i--)
        *out++ = (uint8_t)(((bits >> (7 * i)) & 0x7F) | 0x80);
    *out = (uint8_t)(bits & 0x7F);
    return size;
}

#define MESSAGE_VALUES 16

PyObject *wire_encode(PyObject *prefix, const int64_t *values, Py_ssize_t count)
{
    uint8_t buf[8 + 5 * MESSAGE_VALUES];
    Py_ssize_t at = PyBytes_GET_SIZE(prefix);
    memcpy(buf, PyBytes_AS_STRING(prefix), (size_t)at);
    for (Py_ssize_t i = 0; i < count; i++)
        at += put_vlq(buf + at, values[i]);
    return PyBytes_FromStringAndSize((const char *)buf, at);
}

const char message_doc[] =
"message(prefix, count, *values) -> bytes\n\n"
"prefix (a message id's VLQ) followed by the VLQ of each of the count integer values.";

PyObject *wire_message(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    (void)self;
    if (nargs < 2 || !PyBytes_Check(args[0])) {
        PyErr_SetString(PyExc_TypeError, "message(prefix: bytes, count, *values)");
        return NULL;
    }
    Py_ssize_t count = PyLong_AsSsize_t(args[1]);
    if (count == -1 && PyErr_Occurred())
        return NULL;
    if (nargs - 2 != count || count > MESSAGE_VALUES) {
        PyErr_Format(PyExc_TypeError, "%zd parameters, not %zd", count, nargs - 2);
        return NULL;
    }
    Py_ssize_t plen = PyBytes_GET_SIZE(args[0]);
    if (plen > 8) {
        PyErr_SetString(PyExc_ValueError, "a message id prefix is at most 8 bytes");
        return NULL;
    }
    int64_t values[MESSAGE_VALUES];
    for (Py_ssize_t i = 0; i < count; i++) {
        values[i] = PyLong_AsLongLong(args[2 + i]);
        if (values[i] == -1 && PyErr_Occurred())
            return NULL;
    }
    return wire_encode(args[0], values, count);
}

static uint16_t crc_table[256]; /* filled at import: the reflected polynomial 0x8408 */

void wire_init(void)
{
    for (unsigned byte = 0; byte < 256; byte++) {
        uint16_t crc = (uint16_t)byte;
        for (int bit = 0; bit < 8; bit++)
            crc = (crc & 1) ? (uint16_t)((crc >> 1) ^ 0x8408) : (uint16_t)(crc >> 1);
        crc_table[byte] = crc;
    }
}

/* CRC-16/MCRF4XX a byte at a time from the table (as codec.py's docstring says) */
static uint16_t crc16_of(const uint8_t *data, Py_ssize_t len, uint16_t crc)
{
    for (Py_ssize_t i = 0; i < len; i++)
        crc = (uint16_t)((crc >> 8) ^ crc_table[(crc ^ data[i]) & 0xFF]);
    return crc;
}

/* The block checksum of `data`, for the link's thread (_serialq.c). */
uint16_t wire_crc16_of(const uint8_t *data, Py_ssize_t len)
{
    return crc16_of(data, len, 0xFFFF);
}

const char crc16_doc[] =
"crc16(data) -> int\n\nThe block checksum: CRC-16/MCRF4XX (CCITT polynomial, reflected,\n"
"initial 0xFFFF).";

PyObject *wire_crc16(PyObject *self, PyObject *arg)
{
    (void)self;
    Py_buffer view;
    if (PyObject_GetBuffer(arg, &view, PyBUF_SIMPLE) < 0)
        return NULL;
    uint16_t crc = crc16_of(view.buf, view.len, 0xFFFF);
    PyBuffer_Release(&view);
    return PyLong_FromLong(crc);
}

const char frame_doc[] =
"frame(head, payload) -> bytes\n\n"
"One message block: <length><head><payload><crc16 hi><crc16 lo><0x7e> (the caller checks\n"
"the payload's length: at most 59 bytes).";

PyObject *wire_frame(PyObject *self, PyObject *args)
{
    (void)self;
    int head;
    Py_buffer view;
    if (!PyArg_ParseTuple(args, "iy*", &head, &view))
        return NULL;
    if (view.len > 59) {
        PyBuffer_Release(&view);
        PyErr_SetString(PyExc_ValueError, "a block's payload is at most 59 bytes");
        return NULL;
    }
    uint8_t buf[64];
    Py_ssize_t n = view.len;
    buf[0] = (uint8_t)(n + 5);
    buf[1] = (uint8_t)head;
    memcpy(buf + 2, view.buf, (size_t)n);
    PyBuffer_Release(&view);
    uint16_t crc = crc16_of(buf, n + 2, 0xFFFF);
    buf[n + 2] = (uint8_t)(crc >> 8);
    buf[n + 3] = (uint8_t)(crc & 0xFF);
    buf[n + 4] = 0x7E;
    return PyBytes_FromStringAndSize((const char *)buf, n + 5);
}


