/* The words of a plain G-code line, in C: what parse_line's fast path reads with a dozen
 * calls per line (server/gcode/parser.py), in one.
 *
 * words(text) -> (letters, values) | None
 *
 * A plain line is ASCII words, each a letter and a number, with spaces anywhere (dropped,
 * inside numbers too: "X1 0" is X10). letters: the word letters in order, upper-case;
 * values: each number as Python's float() reads it (PyOS_string_to_double, the same
 * conversion). None for any other line (empty, a comment, a checksum, a repeated letter, a
 * letter without a number, a number that is not [+-](digits[.digits]|.digits), a number over
 * MAX_MAGNITUDE, any other character): the parser's general path reads those and finds their
 * errors.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>

#define MAX_NUMBER 64        /* characters of one number */
#define MAX_MAGNITUDE 1e9    /* parser.MAX_MAGNITUDE */

static int is_letter(unsigned char c) { return (c | 0x20) >= 'a' && (c | 0x20) <= 'z'; }

/* Whether number[0:length] is [+-]?(digits(.digits?)?|.digits), the numbers float() reads
 * from these characters. */
static int is_number(const char *number, Py_ssize_t length)
{
    Py_ssize_t i = (number[0] == '+' || number[0] == '-') ? 1 : 0;
    int digits = 0, dots = 0;
    for (; i < length; i++) {
        if (number[i] >= '0' && number[i] <= '9')
            digits++;
        else if (number[i] == '.' && dots++ == 0)
            continue;
        else
            return 0;
    }
    return digits > 0;
}

/* The number after a letter, from text[*at] up to the next letter: its value in *value, 1;
 * 0 when it is not a plain number. */
static int read_number(const unsigned char *text, Py_ssize_t length, Py_ssize_t *at,
                       double *value)
{
    char number[MAX_NUMBER + 1];
    Py_ssize_t size = 0, i = *at;
    for (; i < length && !is_letter(text[i]); i++) {
        unsigned char c = text[i];
        if (c == ' ')
            continue;
        if (!((c >= '0' && c <= '9') || c == '.' || c == '+' || c == '-') || size == MAX_NUMBER)
            return 0;
        number[size++] = (char)c;
    }
    *at = i;
    if (size == 0 || !is_number(number, size))
        return 0;
    number[size] = '\0';
    char *end = NULL;
    *value = PyOS_string_to_double(number, &end, NULL);
    if (*value == -1.0 && PyErr_Occurred()) {
        PyErr_Clear();
        return 0;
    }
    return end == number + size && fabs(*value) <= MAX_MAGNITUDE;
}

static PyObject *words(PyObject *module, PyObject *text)
{
    (void)module;
    if (!PyUnicode_Check(text)) {
        PyErr_SetString(PyExc_TypeError, "words() takes a str");
        return NULL;
    }
    if (!PyUnicode_IS_ASCII(text))
        Py_RETURN_NONE;
    const unsigned char *data = PyUnicode_1BYTE_DATA(text);
    Py_ssize_t length = PyUnicode_GET_LENGTH(text), at = 0;
    char letters[26];  /* one word per letter at most */
    double values[26];
    unsigned int seen = 0;
    int count = 0;
    for (;;) {
        while (at < length && data[at] == ' ')
            at++;
        if (at == length)
            break;
        if (!is_letter(data[at]))
            Py_RETURN_NONE;
        char letter = (char)(data[at++] & ~0x20);
        unsigned int bit = 1u << (letter - 'A');
        if (seen & bit)
            Py_RETURN_NONE;  /* a repeated word: the general path's error */
        seen |= bit;
        if (!read_number(data, length, &at, &values[count]))
            Py_RETURN_NONE;
        letters[count++] = letter;
    }
    if (count == 0)
        Py_RETURN_NONE;
    PyObject *list = PyList_New(count);
    if (list == NULL)
        return NULL;
    for (int i = 0; i < count; i++) {
        PyObject *value = PyFloat_FromDouble(values[i]);
        if (value == NULL) {
            Py_DECREF(list);
            return NULL;
        }
        PyList_SET_ITEM(list, i, value);
    }
    PyObject *string = PyUnicode_FromStringAndSize(letters, count);
    if (string == NULL) {
        Py_DECREF(list);
        return NULL;
    }
    PyObject *result = PyTuple_Pack(2, string, list);
    Py_DECREF(string);
    Py_DECREF(list);
    return result;
}

static PyMethodDef methods[] = {
    {"words", words, METH_O,
     "words(text) -> (letters, values) of a plain G-code line, or None (see the module)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_words",
    "The words of a plain G-code line, in C (parse_line's fast path).", -1, methods,
    NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__words(void) { return PyModule_Create(&module); }
