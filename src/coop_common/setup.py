"""colcon's ament_python set-up of coop_common (its package.xml says what it is)."""
from setuptools import find_packages, setup

package_name = 'coop_common'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    package_data={package_name: ['data/*.yaml', 'data/*.xml']},
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='Coop Field Robots maintainers',
    maintainer_email='maintainers@coop-field-robots.org',
    description='Shared pieces of the cooperative field robot graph.',
    license='Apache-2.0',
    entry_points={'console_scripts': []},
)
