"""hwgw's web page in headless Chromium, driven by selenium (a browser and a driver we
did not write): prints one JSON object of what a person would have seen and done.

usage: web_page.py URL LIVE_PORT SET_PORT VALUE TOKEN SCREENSHOT
"""

import json
import sys
import time

from selenium import webdriver
from selenium.webdriver.chrome.service import Service
from selenium.webdriver.common.by import By
from selenium.webdriver.support.ui import Select, WebDriverWait

url, live_port, set_port, value, token, screenshot = sys.argv[1:7]

options = webdriver.ChromeOptions()
for a in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--disable-gpu",
          "--window-size=1280,1400"):
    options.add_argument(a)
options.binary_location = "/usr/bin/chromium"
driver = webdriver.Chrome(service=Service("/usr/bin/chromedriver"), options=options)
out = {}
try:
    driver.get(url)
    wait = WebDriverWait(driver, 30)
    cell = "value-" + live_port

    def shown():
        t = driver.find_element(By.ID, cell).text
        return t if t not in ("", "…") else False

    first = wait.until(lambda d: shown())
    began = time.monotonic()
    changed = WebDriverWait(driver, 10, poll_frequency=0.02).until(
        lambda d: (shown() if shown() != first else False))
    out["live"] = {"first": first, "changed": changed, "after_s": time.monotonic() - began}

    wait.until(lambda d: len(d.find_elements(By.CSS_SELECTOR, "#devices tbody tr")) > 0)
    out["devices"] = [[td.text for td in tr.find_elements(By.TAG_NAME, "td")][:3]
                      for tr in driver.find_elements(By.CSS_SELECTOR, "#devices tbody tr")]
    out["health"] = driver.find_element(By.ID, "health").text
    # The plots have a few samples by now.
    time.sleep(1.5)
    driver.save_screenshot(screenshot)

    def set_with(t):
        form = driver.find_element(By.ID, "set-form")
        if not form.is_displayed():
            return {"form": "hidden"}
        Select(driver.find_element(By.ID, "set-port")).select_by_visible_text(set_port)
        for field, text in (("set-value", value), ("set-token", t)):
            e = driver.find_element(By.ID, field)
            e.clear()
            e.send_keys(text)
        result = driver.find_element(By.ID, "set-result")
        driver.execute_script("arguments[0].removeAttribute('data-status')", result)
        driver.find_element(By.ID, "set-button").click()
        wait.until(lambda d: result.get_attribute("data-status"))
        return {"status": int(result.get_attribute("data-status")), "text": result.text}

    out["set_without_token"] = set_with("not the token")
    out["set"] = set_with(token)
    out["console"] = [e["message"] for e in driver.get_log("browser")
                      if e.get("level") == "SEVERE"]
finally:
    driver.quit()
print(json.dumps(out))
