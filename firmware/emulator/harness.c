/*
 * magcal-emu: run the real firmware ELF as an ATmega328P at 16 MHz under simavr, with
 *   - UART0 bridged to a pty of our own (printed as "PTY /dev/pts/N" on stdout); writes to the
 *     pty block, so a host that stops reading pauses the simulation instead of losing bytes;
 *   - the TWI bus answered by the register model (mpu9150_model.c) of the chip --chip names:
 *     mpu9150 (AK8975, the default), mpu9250 or mpu9255 (AK8963), icm20948 (AK09916);
 *   - the field coming from the host over stdio: for each completed measurement the harness
 *     prints "M <t_us> <k> <bits>" (bits: the resolution the firmware set, 13, 14 or 16) and
 *     reads back "<hx> <hy> <hz> <hofl> <temp_raw> [<ax> <ay> <az>]" in the chip's counts at that
 *     resolution, the accelerometer's at +-2 g (none: 0, 0, +1 g, a board lying flat)
 *     (or a fixed field with --field, for use without a host);
 *   - EEPROM kept in a file across restarts (--eeprom);
 *   - the CPU started only once a host has opened the pty (and restarted when a host opens it
 *     again after a close, like the DTR reset of an Uno); SIGUSR1 resets the board at once;
 *   - simulated time paced to the wall clock with --pace.
 *
 * usage: magcal-emu [--chip NAME] [--eeprom FILE] [--field hx,hy,hz] [--asa a,b,c] [--self-test x,y,z]
 *                   [--addr 0x68|0x69] [--faults N] [--measure-us N] [--pace] [--boot-delay-ms N] firmware.elf
 */
#define _GNU_SOURCE
#include <errno.h>
#include <fcntl.h>
#include <poll.h>
#include <signal.h>
#include <stdint.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

#include <simavr/avr_eeprom.h>
#include <simavr/avr_twi.h>
#include <simavr/avr_uart.h>
#include <simavr/sim_avr.h>
#include <simavr/sim_elf.h>

#include "mpu9150_model.h"

#define EEPROM_SIZE 1024
#define FREQ_HZ 16000000UL
#define RUN_CHUNK 2000 /* instructions between housekeeping (about 0.15 ms simulated) */

static volatile sig_atomic_t g_stop, g_reset_req;

typedef struct {
    avr_t *avr;
    mpu_model *model;
    int pty;
    int uart_xon;
    uint8_t inbuf[512];
    size_t in_head, in_len;
    const char *eeprom_path;
    uint8_t eeprom_saved[EEPROM_SIZE];
    int use_field;
    int16_t field[3];
    uint64_t k;
    int pace;
    struct timespec wall0;
    uint64_t cycle0;
} harness;

static void on_signal(int sig)
{
    if (sig == SIGUSR1)
        g_reset_req = 1;
    else
        g_stop = 1;
}

/* simavr logs to stdout by default; stdout is the provider channel, so send logs to stderr */
static void log_to_stderr(struct avr_t *avr, const int level, const char *fmt, va_list ap)
{
    if (avr && level > avr->log)
        return;
    vfprintf(stderr, fmt, ap);
}

/* simavr's own sleep hook usleep()s for the time the AVR sleeps; we pace (or not) ourselves */
static void no_wall_sleep(struct avr_t *avr, avr_cycle_count_t how_long)
{
    (void)avr;
    (void)how_long;
}

static uint64_t sim_us(const harness *h) { return (uint64_t)h->avr->cycle / (FREQ_HZ / 1000000UL); }

static void die(const char *what)
{
    fprintf(stderr, "magcal-emu: %s\n", what);
    exit(2);
}

/* ---- field provider --------------------------------------------------------------------- */
static int provide(void *ctx, uint64_t t_us, mpu_measurement *out)
{
    harness *h = ctx;
    uint64_t k = h->k++;
    if (h->use_field) {
        out->hx = h->field[0];
        out->hy = h->field[1];
        out->hz = h->field[2];
        out->hofl = 0;
        out->temp_raw = -2150;
        out->az = 16384; /* lying flat */
        return 0;
    }
    printf("M %llu %llu %d\n", (unsigned long long)t_us, (unsigned long long)k, mpu_model_mag_bits(h->model));
    fflush(stdout);
    char line[128];
    while (!fgets(line, sizeof line, stdin)) {
        if (ferror(stdin) && errno == EINTR && !g_stop) { /* a reset request: keep waiting */
            clearerr(stdin);
            continue;
        }
        g_stop = 1; /* the host is gone */
        return -1;
    }
    int hx, hy, hz, hofl, temp, ax = 0, ay = 0, az = 16384;
    int got = sscanf(line, "%d %d %d %d %d %d %d %d", &hx, &hy, &hz, &hofl, &temp, &ax, &ay, &az);
    if (got != 5 && got != 8) {
        fprintf(stderr, "magcal-emu: bad provider reply: %s", line);
        return -1;
    }
    out->hx = (int16_t)hx;
    out->hy = (int16_t)hy;
    out->hz = (int16_t)hz;
    out->hofl = (uint8_t)hofl;
    out->temp_raw = (int16_t)temp;
    out->ax = (int16_t)ax;
    out->ay = (int16_t)ay;
    out->az = (int16_t)az;
    return 0;
}

/* ---- TWI: the AVR is the master, the model answers as the slaves ------------------------- */
static void twi_hook(struct avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    harness *h = param;
    avr_twi_msg_irq_t v;
    v.u.v = value;
    uint64_t t = sim_us(h);
    avr_irq_t *in = avr_io_getirq(h->avr, AVR_IOCTL_TWI_GETIRQ(0), TWI_IRQ_INPUT);
    if (v.u.twi.msg & TWI_COND_STOP)
        mpu_model_stop(h->model, t);
    if (v.u.twi.msg & TWI_COND_START) {
        uint8_t a = v.u.twi.addr;
        if (mpu_model_start(h->model, a >> 1, a & 1, t) == 0)
            avr_raise_irq(in, avr_twi_irq_msg(TWI_COND_ACK, a, 1));
        return;
    }
    if (v.u.twi.msg & TWI_COND_WRITE) {
        if (mpu_model_write(h->model, v.u.twi.data, t) == 0)
            avr_raise_irq(in, avr_twi_irq_msg(TWI_COND_ACK, v.u.twi.addr, 1));
    } else if (v.u.twi.msg & TWI_COND_READ) {
        uint8_t b = 0xFF;
        mpu_model_read(h->model, &b, t);
        avr_raise_irq(in, avr_twi_irq_msg(TWI_COND_READ, v.u.twi.addr, b));
    }
}

/* ---- UART <-> pty ------------------------------------------------------------------------ */
static void uart_out_hook(struct avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    harness *h = param;
    uint8_t b = (uint8_t)value;
    for (;;) { /* blocking: a slow reader pauses the simulation, nothing is dropped */
        ssize_t n = write(h->pty, &b, 1);
        if (n == 1)
            return;
        if (n < 0 && errno == EINTR) {
            if (g_stop)
                return;
            continue;
        }
        return; /* EIO: nobody has the port open; bytes go nowhere, as on a real board */
    }
}

static void uart_xon_hook(struct avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)value;
    ((harness *)param)->uart_xon = 1;
}

static void uart_xoff_hook(struct avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)value;
    ((harness *)param)->uart_xon = 0;
}

static void feed_uart(harness *h)
{
    avr_irq_t *in = avr_io_getirq(h->avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_INPUT);
    while (h->in_len && h->uart_xon) {
        avr_raise_irq(in, h->inbuf[h->in_head]);
        h->in_head = (h->in_head + 1) % sizeof h->inbuf;
        h->in_len--;
    }
}

/* 1 while a host has the pty open (no POLLHUP on the master); reads pending input. */
static int service_pty(harness *h)
{
    struct pollfd p = {.fd = h->pty, .events = POLLIN};
    if (poll(&p, 1, 0) < 0)
        return 1;
    if (p.revents & POLLHUP)
        return 0;
    if ((p.revents & POLLIN) && h->in_len < sizeof h->inbuf) {
        size_t tail = (h->in_head + h->in_len) % sizeof h->inbuf;
        size_t room = sizeof h->inbuf - h->in_len;
        if (tail + room > sizeof h->inbuf)
            room = sizeof h->inbuf - tail;
        ssize_t n = read(h->pty, h->inbuf + tail, room);
        if (n > 0)
            h->in_len += (size_t)n;
    }
    return 1;
}

static int open_pty(void)
{
    int m = posix_openpt(O_RDWR | O_NOCTTY);
    if (m < 0 || grantpt(m) || unlockpt(m))
        die("cannot create a pty");
    /* Open the slave once and close it: from then on the master reports POLLHUP exactly while
     * no host has the port open. Raw mode is set here; a host may change it. */
    int s = open(ptsname(m), O_RDWR | O_NOCTTY);
    if (s < 0)
        die("cannot open the pty slave");
    struct termios tio;
    if (tcgetattr(s, &tio) == 0) {
        cfmakeraw(&tio);
        tcsetattr(s, TCSANOW, &tio);
    }
    close(s);
    return m;
}

/* ---- EEPROM file ------------------------------------------------------------------------- */
static void eeprom_load(harness *h)
{
    uint8_t buf[EEPROM_SIZE];
    memset(buf, 0xFF, sizeof buf);
    if (h->eeprom_path) {
        FILE *f = fopen(h->eeprom_path, "rb");
        if (f) {
            size_t n = fread(buf, 1, sizeof buf, f);
            (void)n; /* a short file leaves the rest blank */
            fclose(f);
        }
    }
    avr_eeprom_desc_t d = {.ee = buf, .offset = 0, .size = EEPROM_SIZE};
    avr_ioctl(h->avr, AVR_IOCTL_EEPROM_SET, &d);
    memcpy(h->eeprom_saved, buf, sizeof buf);
}

static void eeprom_save_if_changed(harness *h)
{
    if (!h->eeprom_path)
        return;
    avr_eeprom_desc_t d = {.ee = NULL, .offset = 0, .size = EEPROM_SIZE};
    avr_ioctl(h->avr, AVR_IOCTL_EEPROM_GET, &d);
    if (!d.ee || memcmp(d.ee, h->eeprom_saved, EEPROM_SIZE) == 0)
        return;
    char tmp[4096];
    snprintf(tmp, sizeof tmp, "%s.tmp%d", h->eeprom_path, (int)getpid());
    FILE *f = fopen(tmp, "wb");
    if (!f)
        return;
    size_t n = fwrite(d.ee, 1, EEPROM_SIZE, f);
    if (fclose(f) == 0 && n == EEPROM_SIZE && rename(tmp, h->eeprom_path) == 0)
        memcpy(h->eeprom_saved, d.ee, EEPROM_SIZE);
    else
        unlink(tmp);
}

/* ---- pacing ------------------------------------------------------------------------------ */
static void pace(harness *h)
{
    struct timespec now;
    clock_gettime(CLOCK_MONOTONIC, &now);
    double wall = (now.tv_sec - h->wall0.tv_sec) + (now.tv_nsec - h->wall0.tv_nsec) * 1e-9;
    double sim = (double)(h->avr->cycle - h->cycle0) / FREQ_HZ;
    if (sim > wall + 0.002) {
        double d = sim - wall;
        struct timespec ts = {(time_t)d, (long)((d - (time_t)d) * 1e9)};
        nanosleep(&ts, NULL);
    } else if (wall > sim + 0.5) { /* far behind (host paused us): do not race to catch up */
        h->wall0 = now;
        h->cycle0 = h->avr->cycle;
    }
}

static void restart_clock(harness *h)
{
    clock_gettime(CLOCK_MONOTONIC, &h->wall0);
    h->cycle0 = h->avr->cycle;
}

static void sleep_ms(int ms)
{
    struct timespec ts = {ms / 1000, (long)(ms % 1000) * 1000000L};
    nanosleep(&ts, NULL);
}

/* With a host process on stdin (the provider), its end of the pipe closing means it is gone:
 * stop instead of running on as an orphan. */
static int parent_gone(const harness *h)
{
    if (h->use_field)
        return 0;
    struct pollfd p = {.fd = 0, .events = 0};
    return poll(&p, 1, 0) > 0 && (p.revents & (POLLHUP | POLLERR));
}

/* Wait until a host opens the pty, then give it time to finish opening (pyserial flushes the
 * input when it opens a port: a hello sent earlier would be lost). 0 when asked to stop. */
static int wait_for_host(harness *h, int boot_delay_ms)
{
    while (!g_stop && !parent_gone(h)) {
        if (service_pty(h)) {
            sleep_ms(boot_delay_ms);
            h->in_len = 0; /* nothing typed before the boot reaches the board */
            return 1;
        }
        sleep_ms(2);
    }
    return 0;
}

/* Stack high-water mark: SRAM is painted before the CPU starts; at exit the longest run of
 * paint left between the static data and the stack is the RAM never used. */
#define PAINT 0xC5
static void paint_sram(avr_t *avr)
{
    memset(avr->data + 0x100, PAINT, avr->ramend + 1 - 0x100);
}

static void report_stack(avr_t *avr)
{
    unsigned best_len = 0, best_end = 0, run = 0;
    for (unsigned a = 0x100; a <= avr->ramend; a++) {
        run = avr->data[a] == PAINT ? run + 1 : 0;
        if (run > best_len)
            best_len = run, best_end = a;
    }
    fprintf(stderr, "magcal-emu: stack used at most %u bytes; %u bytes of SRAM never touched\n",
            (unsigned)(avr->ramend - best_end), best_len);
}

static const char *const CHIP_NAMES[MPU_CHIP_COUNT] = {
    [MPU_CHIP_MPU9150] = "mpu9150",
    [MPU_CHIP_MPU9250] = "mpu9250",
    [MPU_CHIP_MPU9255] = "mpu9255",
    [MPU_CHIP_ICM20948] = "icm20948",
};

static int chip_of(const char *name)
{
    for (int c = 0; c < MPU_CHIP_COUNT; c++)
        if (!strcmp(name, CHIP_NAMES[c]))
            return c;
    return -1;
}

static void usage(void)
{
    fprintf(stderr, "usage: magcal-emu [--chip mpu9150|mpu9250|mpu9255|icm20948] [--eeprom FILE] "
                    "[--field hx,hy,hz] [--asa a,b,c] [--self-test x,y,z] [--addr 0x68|0x69] [--faults N] [--measure-us N] [--pace] "
                    "[--boot-delay-ms N] [--stack-report] firmware.elf\n");
    exit(2);
}

int main(int argc, char **argv)
{
    harness h;
    memset(&h, 0, sizeof h);
    uint8_t asa[3] = {176, 178, 166};
    unsigned faults = 0, measure_us = 7300, addr = 0x68;
    int chip = MPU_CHIP_MPU9150;
    int16_t self_test[3] = {0, 0, 0};
    int boot_delay_ms = 100, stack_report = 0;
    const char *elf = NULL;
    for (int i = 1; i < argc; i++) {
        const char *a = argv[i];
        const char *val = (i + 1 < argc) ? argv[i + 1] : NULL;
        if (!strcmp(a, "--pace")) {
            h.pace = 1;
        } else if (!strcmp(a, "--stack-report")) {
            stack_report = 1;
        } else if (!strcmp(a, "--chip") && val) {
            if ((chip = chip_of(val)) < 0)
                usage();
            i++;
        } else if (!strcmp(a, "--eeprom") && val) {
            h.eeprom_path = val, i++;
        } else if (!strcmp(a, "--field") && val) {
            int x, y, z;
            if (sscanf(val, "%d,%d,%d", &x, &y, &z) != 3)
                usage();
            h.use_field = 1, h.field[0] = x, h.field[1] = y, h.field[2] = z, i++;
        } else if (!strcmp(a, "--asa") && val) {
            unsigned x, y, z;
            if (sscanf(val, "%u,%u,%u", &x, &y, &z) != 3 || x > 255 || y > 255 || z > 255)
                usage();
            asa[0] = x, asa[1] = y, asa[2] = z, i++;
        } else if (!strcmp(a, "--self-test") && val) {
            int x, y, z;
            if (sscanf(val, "%d,%d,%d", &x, &y, &z) != 3)
                usage();
            self_test[0] = (int16_t)x, self_test[1] = (int16_t)y, self_test[2] = (int16_t)z, i++;
        } else if (!strcmp(a, "--addr") && val) {
            addr = (unsigned)strtoul(val, NULL, 0), i++;
        } else if (!strcmp(a, "--faults") && val) {
            faults = (unsigned)strtoul(val, NULL, 0), i++;
        } else if (!strcmp(a, "--measure-us") && val) {
            measure_us = (unsigned)strtoul(val, NULL, 0), i++;
        } else if (!strcmp(a, "--boot-delay-ms") && val) {
            boot_delay_ms = atoi(val), i++;
        } else if (a[0] != '-' && !elf) {
            elf = a;
        } else {
            usage();
        }
    }
    if (!elf)
        usage();

    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_signal;
    sigaction(SIGTERM, &sa, NULL);
    sigaction(SIGINT, &sa, NULL);
    sigaction(SIGHUP, &sa, NULL);
    sa.sa_flags = SA_RESTART; /* a reset request must not break a blocking read or write */
    sigaction(SIGUSR1, &sa, NULL);
    signal(SIGPIPE, SIG_IGN);

    avr_global_logger_set(log_to_stderr);
    elf_firmware_t fw;
    memset(&fw, 0, sizeof fw);
    if (elf_read_firmware(elf, &fw))
        die("cannot read the firmware ELF");
    h.avr = avr_make_mcu_by_name("atmega328p"); /* Arduino ELFs carry no .mmcu section */
    if (!h.avr)
        die("simavr has no atmega328p");
    avr_init(h.avr);
    h.avr->frequency = FREQ_HZ;
    avr_load_firmware(h.avr, &fw);
    paint_sram(h.avr);
    h.avr->log = LOG_ERROR;
    h.avr->sleep = no_wall_sleep;

    h.model = calloc(1, mpu_model_size());
    if (!h.model)
        die("out of memory");
    mpu_model_init(h.model, (uint8_t)addr, asa, provide, &h);
    mpu_model_set_chip(h.model, chip);
    mpu_model_set_faults(h.model, faults);
    mpu_model_set_measure_us(h.model, measure_us);
    mpu_model_set_self_test(h.model, self_test);

    avr_irq_register_notify(avr_io_getirq(h.avr, AVR_IOCTL_TWI_GETIRQ(0), TWI_IRQ_OUTPUT),
                            twi_hook, &h);
    avr_irq_register_notify(avr_io_getirq(h.avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUTPUT),
                            uart_out_hook, &h);
    avr_irq_register_notify(avr_io_getirq(h.avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUT_XON),
                            uart_xon_hook, &h);
    avr_irq_register_notify(avr_io_getirq(h.avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUT_XOFF),
                            uart_xoff_hook, &h);
    /* no stdio echo of UART bytes: simavr would otherwise print them as log lines */
    uint32_t flags = 0;
    avr_ioctl(h.avr, AVR_IOCTL_UART_GET_FLAGS('0'), &flags);
    flags &= ~AVR_UART_FLAG_STDIO;
    avr_ioctl(h.avr, AVR_IOCTL_UART_SET_FLAGS('0'), &flags);
    h.uart_xon = 1;

    eeprom_load(&h);
    h.pty = open_pty();
    printf("PTY %s\n", ptsname(h.pty));
    fflush(stdout);

    int rc = 0;
    if (!wait_for_host(&h, boot_delay_ms))
        goto done;
    restart_clock(&h);
    int host_open = 1;
    unsigned long iter = 0;
    while (!g_stop) {
        int state = cpu_Running;
        for (int i = 0; i < RUN_CHUNK; i++) {
            state = avr_run(h.avr);
            if (state == cpu_Done || state == cpu_Crashed)
                break;
        }
        if (state == cpu_Done || state == cpu_Crashed) {
            fprintf(stderr, "magcal-emu: the AVR %s\n", state == cpu_Done ? "stopped" : "crashed");
            rc = 1;
            break;
        }
        int open_now = service_pty(&h);
        if (host_open && !open_now) { /* host closed the port: like an Uno, reset on reopen */
            host_open = 0;
            eeprom_save_if_changed(&h);
            if (!wait_for_host(&h, boot_delay_ms))
                break;
            host_open = 1;
            g_reset_req = 1;
        }
        if (g_reset_req) {
            g_reset_req = 0;
            eeprom_save_if_changed(&h);
            h.in_len = 0;
            avr_reset(h.avr);
            h.uart_xon = 1;
            restart_clock(&h);
        }
        feed_uart(&h);
        if (h.pace)
            pace(&h);
        if ((++iter & 63) == 0) {
            eeprom_save_if_changed(&h);
            if (parent_gone(&h))
                break;
        }
    }
done:
    if (stack_report)
        report_stack(h.avr);
    eeprom_save_if_changed(&h);
    close(h.pty);
    return rc;
}
