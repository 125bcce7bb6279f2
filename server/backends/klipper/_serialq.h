/* The link's thread (_serialq.c, _serialq_thread.c): its state, shared by the two files. */
#ifndef MOTIOND_SERIALQ_H
#define MOTIOND_SERIALQ_H
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

#define SQ_INTERNAL __attribute__((visibility("hidden")))

/* _serialq_thread.c: the thread and the protocol it runs (the window, reading, writing) */
SQ_INTERNAL double now_s(void);
SQ_INTERNAL void kick(int fd);
SQ_INTERNAL void set_fault(SerialQueue *s, enum fault fault, const char *text);
SQ_INTERNAL struct sent *inflight_at(SerialQueue *s, int i);
SQ_INTERNAL void flush_out(SerialQueue *s);
SQ_INTERNAL void new_block(SerialQueue *s, const uint8_t *payload, int len, double now);
SQ_INTERNAL double deadline_s(SerialQueue *s);
SQ_INTERNAL void pump(SerialQueue *s, double now);
SQ_INTERNAL void *run(void *arg);
SQ_INTERNAL void *ring_grow(void *ring, size_t entry_size, size_t *cap, size_t *head);

#endif
