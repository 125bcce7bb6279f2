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
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <errno.h>
#include <math.h>
#include <poll.h>
#include <pthread.h>
#include <signal.h>
#include <stdint.h>
#include <string.h>
#include <sys/eventfd.h>
#include <time.h>
#include <unistd.h>

uint16_t wire_crc16_of(const uint8_t *data, Py_ssize_t len);

#define MESSAGE_MIN 5
#define MESSAGE_MAX 64
#define PAYLOAD_MAX (MESSAGE_MAX - MESSAGE_MIN)
#define SYNC 0x7E
#define DEST 0x10
#define SEQ_MASK 0x0F
#define MIN_RTO_S 0.025
#define MAX_RTO_S 2.0
#define MAX_BLOCKS 15       /* in flight at most: a 4-bit ack tells 0 to 15 apart */
#define WINDOW_BLOCKS 12    /* what the window may fill (klippy's MAX_PENDING_BLOCKS), the
                               rest left for send_first */
#define READ_BYTES 4096
#define RX_LIMIT 4096       /* blocks kept for the Python side: reading pauses beyond */

enum fault { NONE, BROKEN, READ, WRITE, HANGUP };

struct message { uint8_t len, keep; uint8_t data[PAYLOAD_MAX]; };
struct sent {
    uint64_t seq;
    uint8_t payload_len, block_len;
    uint8_t block[MESSAGE_MAX];
    double sent_s;
    int retransmitted;
};
struct received { uint8_t len; uint8_t data[PAYLOAD_MAX]; double received_s; };

typedef struct {
    PyObject_HEAD
    pthread_mutex_t lock;
    pthread_t thread;
    int started, closing;
    int fd, wake_fd, notify_fd;
    /* messages waiting for room, a ring */
    struct message *queue;
    size_t queue_cap, queue_head, queue_len, queue_bytes;
    /* the window */
    struct sent inflight[MAX_BLOCKS];
    int inflight_head, inflight_len, bytes_in_flight, window_bytes, max_blocks;
    uint64_t next_seq, acked, last_empty;
    int synced;
    double ignore_naks_until_s, rto_s, srtt_s; /* srtt_s < 0: no measurement yet */
    long retransmits;
    /* the acknowledgement timeout (< 0: none) and what came meanwhile */
    double ack_timeout_s, progress_s;
    long blocks_in, bad_blocks, bad_at_progress;
    /* reading */
    uint8_t in[READ_BYTES + MESSAGE_MAX];
    int in_len;
    struct received *rx;
    size_t rx_cap, rx_head, rx_len;
    /* writing */
    uint8_t *out;
    size_t out_len, out_cap;
    /* the Python side */
    int notify, notified, failed, dead;
    enum fault fault;
    int fault_taken;
    char fault_text[256];
    double thread_deadline_s;
    unsigned long long bytes_sent, bytes_received, wakes, signals, writes;
} SerialQueue;

static double now_s(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + ts.tv_nsec * 1e-9;
}

static void kick(int fd)
{
    uint64_t one = 1;
    ssize_t r = write(fd, &one, sizeof one);
    (void)r; /* a full counter still wakes the reader */
}

static void set_fault(SerialQueue *s, enum fault fault, const char *text)
{
    if (s->fault != NONE)
        return;
    s->fault = fault;
    snprintf(s->fault_text, sizeof s->fault_text, "%s", text);
    s->failed = 1; /* nothing more is read or judged */
    if (fault != BROKEN)
        s->dead = 1; /* nor written */
    if (!s->notified) { /* a fault is always told at once; pull takes the signal */
        s->notified = 1;
        s->signals++;
        kick(s->notify_fd);
    }
}

static struct sent *oldest(SerialQueue *s) { return &s->inflight[s->inflight_head]; }

static struct sent *inflight_at(SerialQueue *s, int i)
{
    return &s->inflight[(s->inflight_head + i) % MAX_BLOCKS];
}

/* -- writing ---------------------------------------------------------------------------- */
static int reserve(uint8_t **buf, size_t *cap, size_t need)
{
    if (need <= *cap)
        return 0;
    size_t cap2 = *cap ? *cap : 256;
    while (cap2 < need)
        cap2 *= 2;
    uint8_t *grown = realloc(*buf, cap2);
    if (grown == NULL)
        return -1;
    *buf = grown;
    *cap = cap2;
    return 0;
}

static void put_out(SerialQueue *s, const uint8_t *data, size_t len)
{
    if (reserve(&s->out, &s->out_cap, s->out_len + len) < 0) {
        set_fault(s, WRITE, "out of memory");
        return;
    }
    memcpy(s->out + s->out_len, data, len);
    s->out_len += len;
    s->bytes_sent += len;
}

static void flush_out(SerialQueue *s)
{
    if (s->dead || !s->out_len)
        return;
    ssize_t written = write(s->fd, s->out, s->out_len);
    if (written < 0) {
        if (errno == EAGAIN || errno == EINTR)
            return;
        set_fault(s, WRITE, strerror(errno));
        s->dead = 1; /* (after a broken stream's fault too) nothing more is written */
        s->out_len = 0;
        return;
    }
    s->writes++;
    memmove(s->out, s->out + written, s->out_len - (size_t)written);
    s->out_len -= (size_t)written;
}

/* -- the window ------------------------------------------------------------------------- */
static void moved(SerialQueue *s, double now)
{
    s->progress_s = now;
    s->blocks_in = 0;
    s->bad_at_progress = s->bad_blocks;
}

static int can_send(SerialQueue *s, int size)
{
    return s->inflight_len < s->max_blocks && s->bytes_in_flight + size <= s->window_bytes;
}

static void make_block(SerialQueue *s, const uint8_t *payload, int len, double now)
{
    struct sent *sent = inflight_at(s, s->inflight_len++);
    sent->seq = s->next_seq++;
    sent->payload_len = (uint8_t)len;
    sent->block_len = (uint8_t)(len + MESSAGE_MIN);
    sent->block[0] = sent->block_len;
    sent->block[1] = (uint8_t)(DEST | (sent->seq & SEQ_MASK));
    memcpy(sent->block + 2, payload, (size_t)len);
    uint16_t crc = wire_crc16_of(sent->block, len + 2);
    sent->block[len + 2] = (uint8_t)(crc >> 8);
    sent->block[len + 3] = (uint8_t)(crc & 0xFF);
    sent->block[len + 4] = SYNC;
    sent->sent_s = now;
    sent->retransmitted = 0;
    s->bytes_in_flight += sent->block_len;
    put_out(s, sent->block, sent->block_len);
}

static void new_block(SerialQueue *s, const uint8_t *payload, int len, double now)
{
    if (!s->inflight_len) /* the wait for an acknowledgement starts now */
        moved(s, now);
    make_block(s, payload, len, now);
}

static void resend(SerialQueue *s, double now)
{
    s->retransmits++;
    double rtt = s->srtt_s > MIN_RTO_S / 5 ? s->srtt_s : MIN_RTO_S / 5;
    s->ignore_naks_until_s = now + 2.0 * rtt;
    for (int i = 0; i < s->inflight_len; i++) {
        struct sent *sent = inflight_at(s, i);
        sent->sent_s = now;
        sent->retransmitted = 1;
        put_out(s, sent->block, sent->block_len);
    }
}

static void measure(SerialQueue *s, double rtt)
{
    s->srtt_s = s->srtt_s < 0 ? rtt : 0.875 * s->srtt_s + 0.125 * rtt;
    double rto = 3.0 * s->srtt_s;
    s->rto_s = rto < MIN_RTO_S ? MIN_RTO_S : rto > MAX_RTO_S ? MAX_RTO_S : rto;
}

static void acknowledge(SerialQueue *s, uint64_t rseq, double now)
{
    while (s->inflight_len && oldest(s)->seq < rseq) {
        struct sent *sent = oldest(s);
        s->bytes_in_flight -= sent->block_len;
        if (!sent->retransmitted)
            measure(s, now - sent->sent_s);
        s->inflight_head = (s->inflight_head + 1) % MAX_BLOCKS;
        s->inflight_len--;
    }
    s->acked = rseq;
}

/* Number from the MCU's expected block on: what was in flight is framed again. */
static void adopt(SerialQueue *s, uint64_t rseq, double now)
{
    struct sent old[MAX_BLOCKS];
    int count = s->inflight_len;
    for (int i = 0; i < count; i++)
        old[i] = *inflight_at(s, i);
    s->inflight_len = 0;
    s->bytes_in_flight = 0;
    s->acked = s->next_seq = s->last_empty = rseq;
    for (int i = 0; i < count; i++)
        make_block(s, old[i].block + 2, old[i].payload_len, now);
}

/* A block from the MCU acknowledging up to seq4; -1 if the MCU restarted (fault set). */
static int on_block(SerialQueue *s, int seq4, int empty, double now)
{
    uint64_t rseq = s->acked + (((uint64_t)seq4 - s->acked) & SEQ_MASK);
    if (!s->synced) {
        if (empty || rseq > s->next_seq) { /* a nak: an MCU that ran before; adopt its count */
            if (now < s->ignore_naks_until_s)
                return 0;
            s->ignore_naks_until_s = now + s->rto_s;
            adopt(s, rseq, now);
            return 0;
        }
        s->synced = rseq > s->acked;
    }
    if (rseq > s->next_seq) {
        char text[96];
        snprintf(text, sizeof text,
                 "the MCU expects block %d of 16, never sent: it restarted", seq4);
        set_fault(s, BROKEN, text);
        return -1;
    }
    if (rseq > s->acked)
        acknowledge(s, rseq, now);
    if (!empty)
        return 0;
    if (rseq > s->last_empty) { /* an ack (perhaps after the response that acked first) */
        s->last_empty = rseq;
        return 0;
    }
    if (s->inflight_len && now >= s->ignore_naks_until_s)
        resend(s, now);
    return 0;
}

/* Whether a block has waited ack_timeout_s for its acknowledgement (the fault set). */
static int unacknowledged(SerialQueue *s, double now)
{
    if (s->ack_timeout_s < 0 || s->failed || !s->inflight_len
        || now - s->progress_s <= s->ack_timeout_s)
        return 0;
    long bad = s->bad_blocks - s->bad_at_progress;
    char seen[64], text[200];
    if (s->blocks_in || bad)
        snprintf(seen, sizeof seen, "%ld blocks and %ld damaged", s->blocks_in, bad);
    else
        snprintf(seen, sizeof seen, "nothing");
    snprintf(text, sizeof text, "the MCU acknowledged none of %d blocks for %.2f s (it sent %s "
             "meanwhile)", s->inflight_len, now - s->progress_s, seen);
    set_fault(s, BROKEN, text);
    return 1;
}

static double deadline_s(SerialQueue *s)
{
    if (s->failed || !s->inflight_len)
        return INFINITY;
    double deadline = oldest(s)->sent_s + s->rto_s;
    if (s->ack_timeout_s >= 0 && s->progress_s + s->ack_timeout_s < deadline)
        deadline = s->progress_s + s->ack_timeout_s;
    return deadline;
}

static void judge(SerialQueue *s, double now)
{
    if (s->failed || unacknowledged(s, now) || !s->inflight_len)
        return;
    if (now >= oldest(s)->sent_s + s->rto_s) {
        s->rto_s = s->rto_s * 2 < MAX_RTO_S ? s->rto_s * 2 : MAX_RTO_S;
        resend(s, now);
    }
}

/* Queued messages into blocks while the window has room, as many to a block as fit. */
static void pump(SerialQueue *s, double now)
{
    while (s->queue_len && !s->dead) {
        uint8_t payload[PAYLOAD_MAX];
        int len = 0;
        while (s->queue_len) {
            struct message *next = &s->queue[s->queue_head];
            if (len + next->len > PAYLOAD_MAX || !can_send(s, len + next->len + MESSAGE_MIN))
                break;
            memcpy(payload + len, next->data, next->len);
            len += next->len;
            s->queue_bytes -= next->len;
            s->queue_head = (s->queue_head + 1) % s->queue_cap;
            s->queue_len--;
        }
        if (!len)
            break;
        new_block(s, payload, len, now);
    }
    flush_out(s); /* the blocks of a burst in one write */
}

/* -- reading ---------------------------------------------------------------------------- */
static void keep_received(SerialQueue *s, const uint8_t *payload, int len, double now)
{
    if (s->rx_len == s->rx_cap) {
        size_t cap = s->rx_cap ? s->rx_cap * 2 : 64;
        struct received *grown = malloc(cap * sizeof *grown);
        if (grown == NULL) {
            set_fault(s, READ, "out of memory");
            return;
        }
        for (size_t i = 0; i < s->rx_len; i++)
            grown[i] = s->rx[(s->rx_head + i) % s->rx_cap];
        free(s->rx);
        s->rx = grown;
        s->rx_cap = cap;
        s->rx_head = 0;
    }
    struct received *r = &s->rx[(s->rx_head + s->rx_len++) % s->rx_cap];
    r->len = (uint8_t)len;
    memcpy(r->data, payload, (size_t)len);
    r->received_s = now;
}

/* The valid blocks in s->in, each handled; garbage skipped to the next sync byte. */
static void take_blocks(SerialQueue *s, double now)
{
    uint8_t *buf = s->in;
    int pos = 0, len = s->in_len;
    while (pos < len && !s->failed) {
        if (buf[pos] == SYNC) {
            pos++;
            continue;
        }
        int length = buf[pos];
        int bad = length < MESSAGE_MIN || length > MESSAGE_MAX;
        if (!bad && len - pos < length)
            break; /* the rest of the block is on its way */
        if (!bad) {
            const uint8_t *b = buf + pos;
            uint16_t crc = wire_crc16_of(b, length - 3);
            bad = (b[1] & ~SEQ_MASK) != DEST || b[length - 1] != SYNC
                || b[length - 3] != (crc >> 8) || b[length - 2] != (crc & 0xFF);
        }
        if (bad) { /* skip to the byte after the next sync */
            s->bad_blocks++;
            const uint8_t *sync = memchr(buf + pos, SYNC, (size_t)(len - pos));
            pos = sync == NULL ? len : (int)(sync - buf) + 1;
            continue;
        }
        const uint8_t *b = buf + pos;
        pos += length;
        s->blocks_in++;
        int payload_len = length - MESSAGE_MIN;
        if (on_block(s, b[1] & SEQ_MASK, payload_len == 0, now) < 0)
            break;
        if (payload_len)
            keep_received(s, b + 2, payload_len, now);
    }
    memmove(buf, buf + pos, (size_t)(len - pos));
    s->in_len = len - pos;
}

static void read_device(SerialQueue *s, short revents)
{
    ssize_t got = read(s->fd, s->in + s->in_len, READ_BYTES);
    if (got == 0 && !(revents & (POLLHUP | POLLERR | POLLNVAL)))
        got = read(s->fd, s->in + s->in_len, READ_BYTES); /* a raw tty reads empty too */
    if (got < 0) {
        if (errno == EAGAIN || errno == EINTR)
            return;
        set_fault(s, READ, strerror(errno));
        return;
    }
    if (got == 0) {
        set_fault(s, HANGUP, "closed");
        return;
    }
    double now = now_s();
    s->bytes_received += (unsigned long long)got;
    s->in_len += (int)got;
    uint64_t acked = s->acked;
    size_t before = s->rx_len;
    take_blocks(s, now);
    if (s->acked != acked)
        moved(s, now);
    else if (unacknowledged(s, now)) /* a board that talks but never acknowledges */
        return;
    pump(s, now);
    if (s->rx_len > before && s->notify && !s->notified) {
        s->notified = 1;
        s->signals++;
        kick(s->notify_fd);
    }
}

static void *run(void *arg)
{
    SerialQueue *s = arg;
    sigset_t all;
    sigfillset(&all);
    pthread_sigmask(SIG_BLOCK, &all, NULL); /* signals are the interpreter's thread's */
    pthread_mutex_lock(&s->lock);
    while (!s->closing) {
        double now = now_s();
        judge(s, now);
        flush_out(s);
        double deadline = deadline_s(s);
        s->thread_deadline_s = deadline;
        struct pollfd fds[2];
        int reading = !s->failed && s->rx_len < RX_LIMIT;
        /* not polled for nothing: a hung-up device reports POLLHUP whatever is asked */
        fds[0].fd = s->dead || !(reading || s->out_len) ? -1 : s->fd;
        fds[0].events = (short)((reading ? POLLIN : 0) | (s->out_len ? POLLOUT : 0));
        fds[1].fd = s->wake_fd;
        fds[1].events = POLLIN;
        fds[0].revents = fds[1].revents = 0;
        struct timespec wait, *timeout = NULL;
        if (deadline < INFINITY) {
            double left = deadline - now;
            if (left < 0)
                left = 0;
            wait.tv_sec = (time_t)left;
            wait.tv_nsec = (long)((left - (double)wait.tv_sec) * 1e9) + 1000; /* past it */
            if (wait.tv_nsec >= 1000000000L) {
                wait.tv_sec++;
                wait.tv_nsec -= 1000000000L;
            }
            timeout = &wait;
        }
        pthread_mutex_unlock(&s->lock);
        int ready = ppoll(fds, 2, timeout, NULL);
        int error = errno;
        pthread_mutex_lock(&s->lock);
        s->wakes++;
        if (ready < 0) {
            if (error == EINTR)
                continue;
            set_fault(s, READ, strerror(error));
            break;
        }
        if (fds[1].revents & POLLIN) {
            uint64_t count;
            ssize_t r = read(s->wake_fd, &count, sizeof count);
            (void)r;
        }
        if (s->closing)
            break;
        if (fds[0].revents & POLLOUT)
            flush_out(s);
        if (reading && fds[0].revents & (POLLIN | POLLHUP | POLLERR | POLLNVAL))
            read_device(s, fds[0].revents);
    }
    pthread_mutex_unlock(&s->lock);
    return NULL;
}

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
        size_t cap = s->queue_cap ? s->queue_cap * 2 : 64;
        struct message *grown = PyMem_RawMalloc(cap * sizeof *grown);
        if (grown == NULL) {
            PyErr_NoMemory();
            return -1;
        }
        for (size_t i = 0; i < s->queue_len; i++)
            grown[i] = s->queue[(s->queue_head + i) % s->queue_cap];
        PyMem_RawFree(s->queue);
        s->queue = grown;
        s->queue_cap = cap;
        s->queue_head = 0;
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

static const char inflight_doc[] =
"inflight() -> list[bytes]\n\nThe payloads of the blocks not yet acknowledged, oldest first.";

static PyObject *sq_inflight(SerialQueue *s, PyObject *unused)
{
    (void)unused;
    PyObject *list = PyList_New(0);
    if (list == NULL)
        return NULL;
    pthread_mutex_lock(&s->lock);
    for (int i = 0; i < s->inflight_len; i++) {
        struct sent *sent = inflight_at(s, i);
        PyObject *b = PyBytes_FromStringAndSize((const char *)sent->block + 2,
                                                sent->payload_len);
        if (b == NULL || PyList_Append(list, b) < 0) {
            Py_XDECREF(b);
            Py_CLEAR(list);
            break;
        }
        Py_DECREF(b);
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
    for (size_t i = 0; i < s->queue_len; i++) {
        struct message *m = &s->queue[(s->queue_head + i) % s->queue_cap];
        PyObject *b = PyBytes_FromStringAndSize((const char *)m->data, m->len);
        if (b == NULL || PyList_Append(list, b) < 0) {
            Py_XDECREF(b);
            Py_CLEAR(list);
            break;
        }
        Py_DECREF(b);
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
    free(s->rx);
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
    if (PyType_Ready(&SerialQueueType) < 0)
        return -1;
    Py_INCREF(&SerialQueueType);
    if (PyModule_AddObject(module, "SerialQueue", (PyObject *)&SerialQueueType) < 0) {
        Py_DECREF(&SerialQueueType);
        return -1;
    }
    return 0;
}
