/* The link's thread (see _serialq.c): writing, the sequence window, reading, and the loop
 * that waits on the device, the wake-up eventfd and the next deadline. Every function here
 * runs with the state's mutex held. */
#include "_serialq.h"

SQ_INTERNAL double now_s(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + ts.tv_nsec * 1e-9;
}

SQ_INTERNAL void kick(int fd)
{
    uint64_t one = 1;
    ssize_t r = write(fd, &one, sizeof one);
    (void)r; /* a full counter still wakes the reader */
}

SQ_INTERNAL void set_fault(SerialQueue *s, enum fault fault, const char *text)
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

SQ_INTERNAL struct sent *inflight_at(SerialQueue *s, int i)
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

SQ_INTERNAL void flush_out(SerialQueue *s)
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

SQ_INTERNAL void new_block(SerialQueue *s, const uint8_t *payload, int len, double now)
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

SQ_INTERNAL double deadline_s(SerialQueue *s)
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
SQ_INTERNAL void pump(SerialQueue *s, double now)
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
/* A ring of ``cap`` entries of ``entry_size`` bytes, full with ``cap`` from ``*head``, with
   twice the room (64 entries at first), its entries moved to the front in order (``*head``
   becomes 0, ``*cap`` doubles); NULL when out of memory (the ring unchanged). Both rings grow
   here: the messages waiting for room (Python's side, with the GIL) and the blocks received
   (this thread, without it: PyMem_Raw* need none). */
SQ_INTERNAL void *ring_grow(void *ring, size_t entry_size, size_t *cap, size_t *head)
{
    size_t grown_cap = *cap ? *cap * 2 : 64;
    uint8_t *grown = PyMem_RawMalloc(grown_cap * entry_size);
    if (grown == NULL)
        return NULL;
    const uint8_t *old = ring;
    for (size_t i = 0; i < *cap; i++)
        memcpy(grown + i * entry_size, old + (*head + i) % *cap * entry_size, entry_size);
    PyMem_RawFree(ring);
    *cap = grown_cap;
    *head = 0;
    return grown;
}

static void keep_received(SerialQueue *s, const uint8_t *payload, int len, double now)
{
    if (s->rx_len == s->rx_cap) {
        struct received *grown = ring_grow(s->rx, sizeof *s->rx, &s->rx_cap, &s->rx_head);
        if (grown == NULL) {
            set_fault(s, READ, "out of memory");
            return;
        }
        s->rx = grown;
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
    if (s->failed) /* (halted while the thread waited) */
        return;
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
    if (s->failed) /* a restart: what waits is not sent to it (the fault is signalled) */
        return;
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

SQ_INTERNAL void *run(void *arg)
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
