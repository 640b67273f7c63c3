/*
 * uno: an Arduino Uno (ATmega328P at 16 MHz, AVCC 5 V) simulated by libsimavr, for hwgw's
 * tests. It loads an Intel .hex firmware, connects UART0 to a pseudo-terminal (simavr's
 * uart_pty), paces the simulation to real time, and takes line commands on stdin:
 *
 *   in P L        drive Arduino pin P (0-19; 14-19 are A0-A5) as an input at level L
 *   adc N MV      put MV millivolts on analog input N (0-5)
 *   wire A B      a jumper: output pin A drives input pin B from now on
 *   unwire A      takes A's jumper off
 *   get P         prints "@ pin P out O level L duty D period_us T edges E"
 *   pullup P      prints "@ pullup P U": U is 1 while P is an input with its pull-up on
 *                 (its PORT bit set, its DDR bit clear)
 *   cycle         prints "@ cycle C" (simulated cycles since reset)
 *   inject HEX    writes the bytes HEX (two hex digits each) to the host's side of the
 *                 line, between what the firmware sends: garbage on the wire
 *
 * Every command is answered by one line starting with "@ " ("@ ok", "@ pin ...", or
 * "@ error ..."): the command has taken effect when its answer is read. At start it prints
 * "@ pty /dev/pts/N" and then "@ ready". End of stdin ends it. Lines without "@ " are
 * simavr's own.
 *
 * Pins are watched through simavr's IO port IRQs: a change is an output edge only while the
 * pin's DDR bit is set. A pin driven with "in" (or by a wire) stays at that level, as with
 * a real driver, though the firmware writes its port's PORT register. The duty of a toggling pin is measured over its last whole period
 * (rise to rise); a pin quiet for more than 4 of its periods (or 50 ms) reads as its level.
 */
#include <errno.h>
#include <poll.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include <unistd.h>

#include "avr_adc.h"
#include "avr_ioport.h"
#include "avr_timer.h"
#include "sim_avr.h"
#include "sim_hex.h"
#include "uart_pty.h"

#define PINS 20
#define FREQ 16000000ULL
/* data-space addresses of DDRB, DDRC, DDRD and PORTB, PORTC, PORTD on the ATmega328P */
static const int ddr_addr[3] = {0x24, 0x27, 0x2A};
static const int port_addr[3] = {0x25, 0x28, 0x2B};

typedef struct {
    char port;        /* 'B', 'C' or 'D' */
    int bit;
    avr_irq_t *irq;
    int level;
    int driving;      /* set while we raise the irq ourselves */
    int ext;          /* the level the harness drives the pin at, or -1 */
    int wire;         /* pin this one drives, or -1 */
    unsigned long long edges;
    avr_cycle_count_t rise_prev, rise_last, fall_last, last_edge;
    double duty;      /* over the last whole period, or -1 */
    avr_cycle_count_t period;
} pin_t;

static avr_t *avr;
static pin_t pins[PINS];
static int reassert; /* an externally driven input was overwritten: drive it again */
static uart_pty_t pty;

static void pin_map(int p, char *port, int *bit) {
    if (p < 8) {
        *port = 'D';
        *bit = p;
    } else if (p < 14) {
        *port = 'B';
        *bit = p - 8;
    } else {
        *port = 'C';
        *bit = p - 14;
    }
}

static int port_index(const pin_t *pin) { return pin->port == 'B' ? 0 : pin->port == 'C' ? 1 : 2; }

static int is_output(const pin_t *pin) {
    return (avr->data[ddr_addr[port_index(pin)]] >> pin->bit) & 1;
}

static int pulled_up(const pin_t *pin) {
    return !is_output(pin) && ((avr->data[port_addr[port_index(pin)]] >> pin->bit) & 1);
}

static void drive(int p, int level) {
    pins[p].ext = level ? 1 : 0;
    pins[p].driving = 1;
    /* simavr drops a raise of the value its IRQ holds already, and an input whose pull-up
     * is on reads high while that value is 0: the raise must always reach the port. */
    pins[p].irq->value = level ? 0 : 1;
    avr_raise_irq(pins[p].irq, level ? 1 : 0);
    pins[p].driving = 0;
}

static void on_pin(struct avr_irq_t *irq, uint32_t value, void *param) {
    (void)irq;
    pin_t *pin = param;
    if (pin->driving)
        return;
    if (!is_output(pin)) {
        /* simavr raises every pin's IRQ with its PORT bit when the firmware writes the
         * PORT register (a digitalWrite on another pin of the port), which sets an input's
         * PIN bit to its pull-up: a pin the harness drives is driven again at once, as a
         * real driver would keep it. */
        if (pin->ext >= 0 && (int)(value & 1) != pin->ext)
            reassert = 1;
        return;
    }
    int level = value & 1;
    if (level == pin->level)
        return;
    avr_cycle_count_t now = avr->cycle;
    pin->level = level;
    pin->edges++;
    pin->last_edge = now;
    if (level) {
        if (pin->rise_last && pin->fall_last > pin->rise_last) {
            pin->period = now - pin->rise_last;
            pin->duty = (double)(pin->fall_last - pin->rise_last) / (double)pin->period;
        }
        pin->rise_prev = pin->rise_last;
        pin->rise_last = now;
    } else {
        pin->fall_last = now;
    }
    if (pin->wire >= 0)
        drive(pin->wire, level);
}

static double duty_now(pin_t *pin) {
    avr_cycle_count_t quiet = avr->cycle - pin->last_edge;
    avr_cycle_count_t limit = pin->period ? 4 * pin->period : 0;
    if (limit < FREQ / 20)
        limit = FREQ / 20;
    if (pin->duty < 0 || quiet > limit)
        return pin->level ? 1.0 : 0.0;
    return pin->duty;
}

static int valid_pin(int p) { return p >= 0 && p < PINS; }

static void command(char *line) {
    int a, b;
    if (sscanf(line, "in %d %d", &a, &b) == 2 && valid_pin(a)) {
        drive(a, b);
        printf("@ ok\n");
    } else if (sscanf(line, "adc %d %d", &a, &b) == 2 && a >= 0 && a < 6 && b >= 0) {
        avr_raise_irq(avr_io_getirq(avr, AVR_IOCTL_ADC_GETIRQ, ADC_IRQ_ADC0 + a), (uint32_t)b);
        printf("@ ok\n");
    } else if (sscanf(line, "wire %d %d", &a, &b) == 2 && valid_pin(a) && valid_pin(b)) {
        pins[a].wire = b;
        drive(b, pins[a].level);
        printf("@ ok\n");
    } else if (sscanf(line, "unwire %d", &a) == 1 && valid_pin(a)) {
        pins[a].wire = -1;
        printf("@ ok\n");
    } else if (sscanf(line, "get %d", &a) == 1 && valid_pin(a)) {
        pin_t *pin = &pins[a];
        printf("@ pin %d out %d level %d duty %.4f period_us %.1f edges %llu\n", a,
               is_output(pin), pin->level, duty_now(pin),
               (double)pin->period * 1e6 / (double)FREQ, pin->edges);
    } else if (sscanf(line, "pullup %d", &a) == 1 && valid_pin(a)) {
        printf("@ pullup %d %d\n", a, pulled_up(&pins[a]));
    } else if (strncmp(line, "inject ", 7) == 0) {
        unsigned char bytes[1024];
        size_t n = 0;
        unsigned int v;
        for (const char *h = line + 7; n < sizeof bytes && sscanf(h, "%2x", &v) == 1; h += 2)
            bytes[n++] = (unsigned char)v;
        ssize_t w = write(pty.port[0].s, bytes, n);
        printf("@ ok %zd\n", w);
    } else if (strncmp(line, "cycle", 5) == 0) {
        printf("@ cycle %llu\n", (unsigned long long)avr->cycle);
    } else {
        printf("@ error unknown command: %s\n", line);
    }
    fflush(stdout);
}

/* Reads what stdin has; runs each whole line. Returns 0 at end of input. */
static int read_commands(void) {
    static char buf[4096];
    static size_t len;
    struct pollfd pfd = {.fd = 0, .events = POLLIN};
    while (poll(&pfd, 1, 0) > 0) {
        if (len == sizeof buf - 1)
            len = 0; /* an overlong line is dropped */
        ssize_t n = read(0, buf + len, sizeof buf - 1 - len);
        if (n <= 0)
            return n < 0 && errno == EINTR;
        len += (size_t)n;
        char *nl;
        while ((nl = memchr(buf, '\n', len))) {
            *nl = 0;
            command(buf);
            size_t used = (size_t)(nl + 1 - buf);
            memmove(buf, nl + 1, len - used);
            len -= used;
        }
    }
    return 1;
}

static unsigned long long now_ns(void) {
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (unsigned long long)t.tv_sec * 1000000000ULL + (unsigned long long)t.tv_nsec;
}

int main(int argc, char **argv) {
    if (argc != 2) {
        fprintf(stderr, "usage: %s FIRMWARE.hex\n", argv[0]);
        return 2;
    }
    avr = avr_make_mcu_by_name("atmega328p");
    if (!avr) {
        fprintf(stderr, "uno: simavr has no atmega328p\n");
        return 1;
    }
    avr_init(avr);
    avr->frequency = FREQ;
    avr->vcc = avr->avcc = avr->aref = 5000;
    ihex_chunk_p chunks = NULL;
    int n = read_ihex_chunks(argv[1], &chunks);
    if (n <= 0) {
        fprintf(stderr, "uno: cannot read %s as Intel hex\n", argv[1]);
        return 1;
    }
    for (int i = 0; i < n; i++)
        if (chunks[i].baseaddr < 0x8000)
            avr_loadcode(avr, chunks[i].data, chunks[i].size, chunks[i].baseaddr);
    free_ihex_chunks(chunks);

    for (int p = 0; p < PINS; p++) {
        pin_t *pin = &pins[p];
        pin_map(p, &pin->port, &pin->bit);
        pin->irq = avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ(pin->port), pin->bit);
        pin->wire = -1;
        pin->ext = -1;
        pin->duty = -1;
        avr_irq_register_notify(pin->irq, on_pin, pin);
    }

    /* The timers' compare outputs (PWM) reach their pins through these IRQs. */
    static const struct { char timer; int comp; int pin; } oc[] = {
        {'0', 0, 6}, {'0', 1, 5}, {'1', 0, 9}, {'1', 1, 10}, {'2', 0, 11}, {'2', 1, 3}};
    for (size_t i = 0; i < sizeof oc / sizeof oc[0]; i++) {
        avr_irq_t *irq = avr_io_getirq(avr, AVR_IOCTL_TIMER_GETIRQ(oc[i].timer),
                                       TIMER_IRQ_OUT_COMP + oc[i].comp);
        if (irq)
            avr_irq_register_notify(irq, on_pin, &pins[oc[i].pin]);
    }

    uart_pty_init(avr, &pty);
    uart_pty_connect(&pty, '0');
    printf("@ pty %s\n@ ready\n", pty.port[0].slavename);
    fflush(stdout);

    unsigned long long start = now_ns();
    avr_cycle_count_t next_check = 0;
    for (;;) {
        int state = avr_run(avr);
        if (state == cpu_Done || state == cpu_Crashed) {
            printf("@ error the AVR stopped (state %d)\n", state);
            fflush(stdout);
            return 1;
        }
        if (reassert) {
            /* within the instruction that overwrote it */
            reassert = 0;
            for (int p = 0; p < PINS; p++)
                if (pins[p].ext >= 0 && !is_output(&pins[p]) &&
                    (int)pins[p].irq->value != pins[p].ext)
                    drive(p, pins[p].ext);
        }
        if (avr->cycle < next_check)
            continue;
        next_check = avr->cycle + FREQ / 2000; /* every 0.5 ms simulated */
        if (!read_commands())
            break;
        unsigned long long sim = avr->cycle * 1000ULL / (FREQ / 1000000ULL);
        unsigned long long wall = now_ns() - start;
        if (sim > wall + 200000ULL) {
            struct timespec d = {.tv_sec = 0, .tv_nsec = (long)(sim - wall)};
            nanosleep(&d, NULL);
        }
    }
    uart_pty_stop(&pty);
    return 0;
}
