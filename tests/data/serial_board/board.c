/*
 * A microcontroller on a serial line, for tests: it speaks serial datagrams with the interface of
 * CVRA's lib/serial-datagram (serial_datagram_send with a send function, a receive handler fed
 * byte by byte that calls back once per good datagram and reports errors), written anew here,
 * and CVRA's message layout: one MessagePack array [name, args] per datagram, floats 32-bit.
 *
 *     board DEVICE SECONDS
 *
 * Every 100 ms it sends ["position", [1.0, 0.5, 0.25]]; every datagram it receives is printed
 * as "got <hex>", and every error as "error <code>", one line each. It serves one call, "ping"
 * (no arguments: one byte, such as an empty map), as calls go on a serial line: the call is
 * ["ping", args, id], the answer [id, [true, "pong"]], the id copied as it came.
 */
#include <errno.h>
#include <fcntl.h>
#include <stdbool.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/select.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

#define END 0xC0
#define ESC 0xDB
#define ESC_END 0xDC
#define ESC_ESC 0xDD

#define RCV_NO_ERROR 0
#define RCV_TOO_LONG 1
#define RCV_CRC_MISMATCH 2
#define RCV_PROTOCOL_ERROR 3

typedef void (*datagram_cb_t)(const void *datagram, size_t len, void *arg);
typedef void (*send_fn_t)(void *arg, const void *p, size_t len);

typedef struct {
    uint8_t *buffer;
    size_t size;
    size_t write_index;
    datagram_cb_t callback;
    void *callback_arg;
    bool error;   /* skipping to the next END */
    bool escaped; /* the byte before was ESC */
} rcv_handler_t;

/* CRC-32 (IEEE 802.3, reflected, as zlib's crc32), bit by bit: a board has no room for tables */
static uint32_t crc32_update(uint32_t crc, const uint8_t *p, size_t len)
{
    crc = ~crc;
    while (len--) {
        crc ^= *p++;
        for (int bit = 0; bit < 8; bit++) {
            crc = (crc >> 1) ^ (0xEDB88320UL & (0U - (crc & 1U)));
        }
    }
    return ~crc;
}

static void send_escaped(const uint8_t *p, size_t len, send_fn_t send, void *arg)
{
    static const uint8_t esc_end[2] = {ESC, ESC_END}, esc_esc[2] = {ESC, ESC_ESC};
    size_t start = 0;
    for (size_t i = 0; i < len; i++) {
        if (p[i] == END || p[i] == ESC) {
            send(arg, p + start, i - start);
            send(arg, p[i] == END ? esc_end : esc_esc, 2);
            start = i + 1;
        }
    }
    send(arg, p + start, len - start);
}

void serial_datagram_send(const void *datagram, size_t len, send_fn_t send, void *arg)
{
    uint32_t crc = crc32_update(0, datagram, len);
    uint8_t tail[4] = {crc >> 24, crc >> 16, crc >> 8, crc};
    static const uint8_t end = END;
    send_escaped(datagram, len, send, arg);
    send_escaped(tail, sizeof tail, send, arg);
    send(arg, &end, 1);
}

void serial_datagram_rcv_handler_init(rcv_handler_t *h, void *buffer, size_t size,
                                      datagram_cb_t callback, void *arg)
{
    memset(h, 0, sizeof *h);
    h->buffer = buffer;
    h->size = size;
    h->callback = callback;
    h->callback_arg = arg;
}

static int frame_end(rcv_handler_t *h)
{
    int result = RCV_NO_ERROR;
    if (h->escaped) {
        result = RCV_PROTOCOL_ERROR;
    } else if (h->write_index < 4) {
        result = RCV_PROTOCOL_ERROR;
    } else {
        size_t len = h->write_index - 4;
        const uint8_t *c = h->buffer + len;
        uint32_t crc = (uint32_t)c[0] << 24 | (uint32_t)c[1] << 16 | (uint32_t)c[2] << 8 | c[3];
        if (crc32_update(0, h->buffer, len) != crc) {
            result = RCV_CRC_MISMATCH;
        } else {
            h->callback(h->buffer, len, h->callback_arg);
        }
    }
    h->write_index = 0;
    h->escaped = false;
    return result;
}

/* feeds bytes; returns the first error met (once per bad frame), else RCV_NO_ERROR */
int serial_datagram_receive(rcv_handler_t *h, const void *in, size_t len)
{
    const uint8_t *p = in;
    int result = RCV_NO_ERROR;
    for (size_t i = 0; i < len; i++) {
        uint8_t byte = p[i];
        int error = RCV_NO_ERROR;
        if (byte == END) {
            if (h->error) {
                h->error = false;
                h->write_index = 0;
                h->escaped = false;
            } else {
                error = frame_end(h);
            }
        } else if (h->error) {
            continue;
        } else if (h->escaped) {
            h->escaped = false;
            if (byte != ESC_END && byte != ESC_ESC) {
                error = RCV_PROTOCOL_ERROR;
            } else if (h->write_index >= h->size) {
                error = RCV_TOO_LONG;
            } else {
                h->buffer[h->write_index++] = byte == ESC_END ? END : ESC;
            }
        } else if (byte == ESC) {
            h->escaped = true;
        } else if (h->write_index >= h->size) {
            error = RCV_TOO_LONG;
        } else {
            h->buffer[h->write_index++] = byte;
        }
        if (error != RCV_NO_ERROR) {
            if (byte != END) {
                h->error = true;
            }
            if (result == RCV_NO_ERROR) {
                result = error;
            }
        }
    }
    return result;
}

/* --- the board ------------------------------------------------------------------------------ */

static void write_all(void *arg, const void *p, size_t len)
{
    int fd = *(int *)arg;
    const uint8_t *b = p;
    while (len > 0) {
        ssize_t n = write(fd, b, len);
        if (n < 0) {
            if (errno == EINTR || errno == EAGAIN) {
                continue;
            }
            perror("write");
            exit(1);
        }
        b += n;
        len -= (size_t)n;
    }
}

static void answer_ping(const uint8_t *call, size_t len, int *fd)
{
    static const uint8_t ping[] = {0x93, 0xA4, 'p', 'i', 'n', 'g'};
    static const uint8_t pong[] = {0x92, 0xC3, 0xA4, 'p', 'o', 'n', 'g'};
    size_t id_at = sizeof ping + 1; /* after the one byte of arguments */
    if (len <= id_at || len - id_at > 9 || memcmp(call, ping, sizeof ping) != 0) {
        return;
    }
    uint8_t answer[1 + 9 + sizeof pong];
    size_t n = 0;
    answer[n++] = 0x92; /* [id, value] */
    memcpy(answer + n, call + id_at, len - id_at);
    n += len - id_at;
    memcpy(answer + n, pong, sizeof pong);
    n += sizeof pong;
    serial_datagram_send(answer, n, write_all, fd);
}

static void print_datagram(const void *datagram, size_t len, void *arg)
{
    const uint8_t *p = datagram;
    printf("got ");
    for (size_t i = 0; i < len; i++) {
        printf("%02x", p[i]);
    }
    printf("\n");
    fflush(stdout);
    answer_ping(p, len, arg);
}

static size_t put_float(uint8_t *out, float value)
{
    uint32_t bits;
    memcpy(&bits, &value, sizeof bits);
    out[0] = 0xCA; /* MessagePack float 32, big-endian */
    out[1] = bits >> 24;
    out[2] = bits >> 16;
    out[3] = bits >> 8;
    out[4] = bits;
    return 5;
}

static size_t position_message(uint8_t *out)
{
    size_t n = 0;
    out[n++] = 0x92; /* [name, args] */
    out[n++] = 0xA0 | 8;
    memcpy(out + n, "position", 8);
    n += 8;
    out[n++] = 0x93; /* [x, y, theta] */
    n += put_float(out + n, 1.0f);
    n += put_float(out + n, 0.5f);
    n += put_float(out + n, 0.25f);
    return n;
}

static double now(void)
{
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return t.tv_sec + t.tv_nsec / 1e9;
}

int main(int argc, char **argv)
{
    if (argc != 3) {
        fprintf(stderr, "usage: %s DEVICE SECONDS\n", argv[0]);
        return 2;
    }
    int fd = open(argv[1], O_RDWR | O_NOCTTY);
    if (fd < 0) {
        perror(argv[1]);
        return 1;
    }
    struct termios tio;
    if (tcgetattr(fd, &tio) == 0) {
        cfmakeraw(&tio);
        cfsetspeed(&tio, B115200);
        tcsetattr(fd, TCSANOW, &tio);
    }
    static uint8_t buffer[512];
    rcv_handler_t handler;
    serial_datagram_rcv_handler_init(&handler, buffer, sizeof buffer, print_datagram, &fd);
    uint8_t message[64];
    size_t message_len = position_message(message);
    double end = now() + atof(argv[2]), next_send = 0;
    while (now() < end) {
        if (now() >= next_send) {
            serial_datagram_send(message, message_len, write_all, &fd);
            next_send = now() + 0.1;
        }
        fd_set readable;
        FD_ZERO(&readable);
        FD_SET(fd, &readable);
        struct timeval wait = {0, 20000};
        if (select(fd + 1, &readable, NULL, NULL, &wait) > 0) {
            uint8_t in[256];
            ssize_t n = read(fd, in, sizeof in);
            if (n <= 0) {
                break; /* the line is gone */
            }
            int error = serial_datagram_receive(&handler, in, (size_t)n);
            if (error != RCV_NO_ERROR) {
                printf("error %d\n", error);
                fflush(stdout);
            }
        }
    }
    return 0;
}
